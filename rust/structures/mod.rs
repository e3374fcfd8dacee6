//! Poisson structures beyond g*, each with its realization and its classical baselines.
//!
//! - [`log_canonical`]: π_ij = c_ij x_i x_j (Lotka–Volterra in any dimension), stepped in
//!   q = ln x where the bracket is the constant matrix c and the groupoid is linear.
//! - [`polynomial`]: any polynomial bivector, through an approximate realization of order n
//!   whose maps and generating function arrive as polynomial coefficients.

pub mod log_canonical;
pub mod polynomial;

pub use log_canonical::{
    ExpMonomial, ExpPolynomial, LearnedExp, LearnedLogBisection, LogBisection, LogCanonical,
    LogClassical, LogMethod, LogSystem, OrthantChecked,
};
pub use polynomial::{
    LearnedPolynomial, LearnedPolynomialBisection, LearnedPolynomialModel, PolynomialBisection,
    PolynomialGenerating, PolynomialRealization, SparsePolynomial,
};
