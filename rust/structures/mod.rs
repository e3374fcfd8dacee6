//! Poisson structures, each with its realization (and, beyond g*, its classical baselines); each
//! plugs into the generic stepper through [`crate::realization::Realization`].
//!
//! - [`lie_poisson`]: Lie–Poisson systems on g* (structure constants, polynomial Hamiltonian,
//!   vector fields), with [`lie_groupoid`], the exact groupoid T*G ⇉ g* in its charts.
//! - [`log_canonical`]: π_ij = c_ij x_i x_j (Lotka–Volterra in any dimension), stepped in
//!   q = ln x where the bracket is the constant matrix c and the groupoid is linear.
//! - [`bivector`]: any polynomial bivector with any smooth Hamiltonian (an expression): its
//!   vector field, for the classical baselines; [`point_vortices`], its straight-line form for
//!   vortices in the plane.
//! - [`polynomial`]: any polynomial bivector, through an approximate realization of order n
//!   whose maps and generating function arrive as polynomial coefficients.

pub mod bivector;
pub mod lie_groupoid;
pub mod lie_poisson;
pub mod log_canonical;
pub mod point_vortices;
pub mod polynomial;
pub mod polynomial_lanes;

pub use log_canonical::{
    ExpMonomial, ExpPolynomial, LearnedExp, LearnedLogBisection, LearnedLogStepper, LogBisection,
    LogCanonical, LogClassical, LogExplicit, LogMethod, LogSystem, LogTaylorLanes, OrthantChecked,
};
pub use polynomial::{
    LearnedPolynomial, LearnedPolynomialBisection, LearnedPolynomialModel, PolynomialBisection,
    PolynomialField, PolynomialGenerating, PolynomialRealization, SparsePolynomial,
};
pub use polynomial_lanes::PolynomialLanes;
