//! Learned generating functions on the log-canonical groupoid: the exact Taylor terms plus a
//! network term.

use nalgebra::{Const, DimMin};

use super::taylor::{log_bisection_lanes, LogLaneGenerating, T_POWERS};
use super::{log_state_in_orthant, ExpPolynomial, LogCanonical};
use crate::dual::{Dual1, Jet2};
use crate::error::CoreError;
use crate::generating::polynomial_lanes::JetLanes;
use crate::generating::{GeneratingFunction, LaneRow, Workspace, MAX_BATCH};
use crate::isa::Isa;
use crate::lanes_bisection::{lane_newton_steps, LaneSolve};
use crate::realization::Generating;
use crate::step::{StepMap, StepResult};
use crate::stepper::BisectionStepper;

/// A learned generating function on the log-canonical groupoid: exact Taylor terms
/// ([`ExpPolynomial`]) plus t^m · N(t, q), the network term of a [`GeneratingFunction`] with
/// plain inputs (t, q) and no polynomial part. Both derivatives are exact: closed form for the
/// Taylor terms, forward-mode duals through the MLP.
#[derive(Clone, Debug, PartialEq)]
pub struct LearnedExp<const N: usize> {
    pub taylor: ExpPolynomial<N>,
    pub network: GeneratingFunction<N>,
}

impl<const N: usize> LearnedExp<N> {
    /// Refuses a network part with polynomial terms of its own (they would be read as
    /// polynomials in q, not in y = e^q).
    pub fn new(
        taylor: ExpPolynomial<N>,
        network: GeneratingFunction<N>,
    ) -> Result<Self, CoreError> {
        if !network.polynomial.terms().is_empty() {
            return Err(CoreError::Invalid(
                "the network part of a log-canonical generating function must hold no \
                 polynomial terms (the Taylor terms are exponential monomials)"
                    .into(),
            ));
        }
        Ok(LearnedExp { taylor, network })
    }
}

impl<const N: usize> Generating<N> for LearnedExp<N> {
    type Workspace = Workspace<N>;
    fn workspace(&self) -> Workspace<N> {
        self.network.workspace()
    }
    fn jet(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Jet2<N> {
        self.taylor.jet_at(t, p) + self.network.jet(t, p, ws)
    }
    fn gradient(&self, t: f64, p: &[f64; N], ws: &mut Workspace<N>) -> Dual1<N> {
        let taylor = self.taylor.jet_at(t, p);
        let net = self.network.gradient(t, p, ws);
        Dual1 {
            v: taylor.v + net.v,
            g: std::array::from_fn(|i| taylor.g[i] + net.g[i]),
        }
    }
}

impl<const N: usize> LogLaneGenerating<N> for LearnedExp<N> {
    const NETWORK: bool = true;

    /// The Taylor terms' gradient alone.
    #[inline(always)]
    fn start_gradient_lanes<const L: usize>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        _: &mut [LaneRow],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
        _: &mut [[[f64; L]; N]; N],
    ) {
        self.taylor.taylor_lanes::<L, false>(t, t_powers, q, g, hs);
    }

    /// The Taylor terms' closed form plus the network term in lanes, its Hessian (with
    /// `NET_HESS`) in `hn`. Only called where the network fits the lanes
    /// ([`GeneratingFunction::network_lanes`]); anywhere else the derivatives are NaN, so that a
    /// misuse fails as NonFinite instead of dropping the term.
    #[inline(always)]
    fn derivatives_lanes<const L: usize, const HESS: bool, const NET_HESS: bool>(
        &self,
        t: f64,
        t_powers: &[f64; T_POWERS],
        q: &[[f64; L]; N],
        buf: &mut [LaneRow],
        g: &mut [[f64; L]; N],
        hs: &mut [[[f64; L]; N]; N],
        hn: &mut [[[f64; L]; N]; N],
    ) {
        self.taylor.taylor_lanes::<L, HESS>(t, t_powers, q, g, hs);
        let Some(net) = self.network.network_lanes() else {
            *g = [[f64::NAN; L]; N];
            return;
        };
        let mut jet = JetLanes {
            v: [0.0; L],
            g: [[0.0; L]; N],
            h: [[[0.0; L]; N]; N],
        };
        net.add_jet_lanes::<N, L, NET_HESS>(t, q, buf, &mut jet);
        for a in 0..N {
            for l in 0..L {
                g[a][l] += jet.g[a][l];
            }
            if NET_HESS {
                for b in a..N {
                    hn[a][b] = jet.h[a][b];
                    hn[b][a] = jet.h[a][b];
                }
            }
        }
    }
}

/// The learned bisection integrator of a log-canonical structure, state q = ln x.
pub type LearnedLogBisection<const N: usize> = BisectionStepper<N, LogCanonical<N>, LearnedExp<N>>;

/// A learned log-canonical integrator as a model steps it: where the network fits the lanes
/// ([`GeneratingFunction::network_lanes`]), the Newton solves run in SIMD lanes (the solve of
/// [`super::LogTaylorLanes`] with the network term added; one trajectory is one lane, so `step`
/// and `step_batch` give the same bits); otherwise one trajectory at a time through dual
/// numbers. Every step is checked to keep x = e^q in the orthant.
pub struct LearnedLogStepper<const N: usize>(pub LearnedLogBisection<N>);

impl<const N: usize> LearnedLogStepper<N> {
    fn in_lanes(&self) -> bool {
        self.0.generating.network.network_lanes().is_some()
    }
}

impl<const N: usize> LaneSolve<N> for LearnedLogStepper<N> {
    #[inline(always)]
    fn block<const L: usize>(
        &self,
        buf: &mut [LaneRow],
        t: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
    ) {
        let n = mu.len();
        let mut q = [[0.0; L]; N];
        let mut on = [false; L];
        for j in 0..n {
            for i in 0..N {
                q[i][j] = mu[j][i];
            }
            on[j] = live[j];
        }
        let mut out = [Ok(Default::default()); L];
        log_bisection_lanes(&self.0, buf, t, &mut q, &on, &mut out);
        for j in (0..n).filter(|&j| on[j]) {
            results[j] = out[j];
            for i in 0..N {
                mu[j][i] = q[i][j];
            }
        }
    }
}

impl<const N: usize> StepMap<N> for LearnedLogStepper<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Workspace = Workspace<N>;
    fn workspace(&self) -> Workspace<N> {
        self.0.workspace()
    }
    fn workspace_bytes(&self) -> usize {
        self.0.workspace_bytes()
    }
    fn step(&self, h: f64, q: &mut [f64; N], ws: &mut Workspace<N>) -> StepResult {
        let mut result = [Ok(Default::default())];
        self.step_batch(h, std::slice::from_mut(q), &[true], &mut result, ws);
        result[0]
    }
    fn batch(&self) -> usize {
        if self.in_lanes() {
            MAX_BATCH
        } else {
            1
        }
    }
    fn step_batch(
        &self,
        h: f64,
        mu: &mut [[f64; N]],
        live: &[bool],
        results: &mut [StepResult],
        ws: &mut Workspace<N>,
    ) {
        if self.in_lanes() {
            let buf = self.0.generating.network.lane_scratch(ws);
            return lane_newton_steps(self, Isa::detect(), buf, h, mu, live, results);
        }
        // OrthantChecked's step, one trajectory at a time.
        for ((m, &l), r) in mu.iter_mut().zip(live).zip(results.iter_mut()) {
            if l {
                *r = self
                    .0
                    .step(h, m, ws)
                    .and_then(|stats| log_state_in_orthant(m).map(|()| stats));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    //! The learned generating function and its model file: the jet is the sum of its parts, a
    //! random network keeps the monomial Casimir to round-off, and files of another or an
    //! unknown structure are refused by name.

    use std::collections::HashMap;

    use safetensors::tensor::TensorView;
    use safetensors::{serialize, Dtype};

    use super::*;
    use crate::generating::{Layer, Mlp, MlpInputs, Polynomial};
    use crate::model::{LogModel, Model, FORMAT};
    use crate::step::{NewtonOptions, StepMap};
    use crate::structures::log_canonical::{ExpMonomial, OrthantChecked};

    /// A fixed tanh MLP R^{1+3} → R with one hidden layer of 5 (weights from a sine pattern).
    fn mlp() -> Mlp {
        let w0: Vec<f64> = (0..20).map(|k| 0.7 * (1.3 * k as f64).sin()).collect();
        let b0: Vec<f64> = (0..5).map(|k| 0.2 * (0.9 * k as f64).cos()).collect();
        let w1: Vec<f64> = (0..5).map(|k| 0.5 * (2.1 * k as f64 + 0.3).sin()).collect();
        Mlp::new(vec![
            Layer::new(4, 5, w0, b0).unwrap(),
            Layer::new(5, 1, w1, vec![0.1]).unwrap(),
        ])
        .unwrap()
    }

    /// S = −t(x₁ + x₂ + x₃) + t b·q + t³ N(t, q) on the 3D structure with Casimir Σ q_i.
    fn learned() -> (LogCanonical<3>, LearnedExp<3>) {
        let c = [[0.0, 1.0, -1.0], [-1.0, 0.0, 1.0], [1.0, -1.0, 0.0]];
        let terms = (0..3)
            .map(|i| {
                let mut exponents = [0; 3];
                exponents[i] = 1;
                ExpMonomial {
                    t_power: 1,
                    exponents,
                    coeff: -1.0,
                }
            })
            .collect();
        let taylor = ExpPolynomial::new(terms, [1.0, 1.5, 2.0]).unwrap();
        let network =
            GeneratingFunction::new(Polynomial::default(), Some(mlp()), 3, MlpInputs::Plain)
                .unwrap();
        (
            LogCanonical::new(c).unwrap(),
            LearnedExp::new(taylor, network).unwrap(),
        )
    }

    #[test]
    fn jet_is_the_sum_of_the_taylor_and_network_jets() {
        let (_, s) = learned();
        let mut ws = Generating::workspace(&s);
        let q = [0.2, -0.4, 0.7];
        let jet = Generating::jet(&s, 0.1, &q, &mut ws);
        let sum = s.taylor.jet_at(0.1, &q) + s.network.jet(0.1, &q, &mut ws);
        assert_eq!(jet, sum);
        let grad = Generating::gradient(&s, 0.1, &q, &mut ws);
        for i in 0..3 {
            assert!((grad.g[i] - jet.g[i]).abs() <= 1e-15);
        }
    }

    #[test]
    fn random_network_keeps_the_casimir_to_round_off() {
        let (realization, generating) = learned();
        let stepper = OrthantChecked(LearnedLogBisection::unit_scale(
            generating,
            realization,
            NewtonOptions::default(),
        ));
        let mut ws = stepper.workspace();
        let mut q = [0.1, -0.2, 0.3];
        let c0: f64 = q.iter().sum();
        for _ in 0..1000 {
            stepper.step(0.05, &mut q, &mut ws).unwrap();
        }
        assert!((q.iter().sum::<f64>() - c0).abs() <= 1e-12);
    }

    /// A log-canonical model file: the 2D structure, S = −t(x₁ + x₂) + t(1, 2)·q, and the
    /// given metadata.
    fn file(meta: &[(&str, &str)]) -> Vec<u8> {
        let f64s = |v: &[f64]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let c = f64s(&[0.0, 1.0, -1.0, 0.0]);
        let powers: Vec<u8> = [1i64, 1, 0, 1, 0, 1]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let coeffs = f64s(&[-1.0, -1.0]);
        let linear = f64s(&[1.0, 2.0]);
        let views = vec![
            (
                "structure.c",
                TensorView::new(Dtype::F64, vec![2, 2], &c).unwrap(),
            ),
            (
                "poly.powers",
                TensorView::new(Dtype::I64, vec![2, 3], &powers).unwrap(),
            ),
            (
                "poly.coeffs",
                TensorView::new(Dtype::F64, vec![2], &coeffs).unwrap(),
            ),
            (
                "poly.linear",
                TensorView::new(Dtype::F64, vec![2], &linear).unwrap(),
            ),
        ];
        let meta: HashMap<String, String> = meta
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        serialize(views, Some(meta)).unwrap()
    }

    #[test]
    fn model_files_name_their_structure() {
        let good = file(&[("format", FORMAT), ("structure", "log_canonical")]);
        let model = LogModel::from_bytes(&good).unwrap();
        assert_eq!((model.dim, model.n_taylor_terms()), (2, 2));
        let err = Model::from_bytes(&good).unwrap_err().to_string();
        assert!(err.contains("structure is 'log_canonical'"), "{err}");
        let odd = file(&[("format", FORMAT), ("structure", "nambu")]);
        let err = LogModel::from_bytes(&odd).unwrap_err().to_string();
        assert!(err.contains("unknown model structure 'nambu'"), "{err}");
        let none = file(&[("format", FORMAT)]);
        let err = LogModel::from_bytes(&none).unwrap_err().to_string();
        assert!(err.contains("'structure' is missing"), "{err}");
    }
}
