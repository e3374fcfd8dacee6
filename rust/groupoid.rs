//! The symplectic groupoid T*SO(3) ⇉ so(3)* in a chart of SO(3) near the identity.
//!
//! Coordinates are (x, p) ∈ R³×R³. `sou` is the spatial momentum, `tar` the body one; units are
//! x = 0. In both charts |sou(x,p)| = |tar(x,p)|, which is why every bisection map keeps the
//! Casimir |μ|² whatever the generating function is.

use crate::dual::Scalar;
use crate::error::StepFailure;

/// A chart of SO(3) near the identity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Chart {
    /// Cayley transform: polynomial, no trigonometry.
    Cayley,
    /// Exponential map: singular at |x| = 2π.
    Exp,
}

/// Largest |x| the exponential chart accepts: c(θ) has a pole at 2π.
pub const EXP_CHART_MAX_ANGLE: f64 = 2.0 * std::f64::consts::PI - 0.1;

/// Taylor coefficients of c(θ) = (1 − (θ/2)cot(θ/2))/θ² in s = θ²: |B₂ₙ|/(2n)!.
const C_SERIES: [f64; 12] = [
    1.0 / 12.0,
    1.0 / 720.0,
    1.0 / 30240.0,
    1.0 / 1209600.0,
    1.0 / 47900160.0,
    691.0 / 1307674368000.0,
    1.0 / 74724249600.0,
    3617.0 / 10670622842880000.0,
    43867.0 / 5109094217170944000.0,
    174611.0 / 802857662698291200000.0,
    77683.0 / 14101100039391805440000.0,
    236364091.0 / 1693824136731743669452800000.0,
];

/// c(s), c'(s), c''(s) for s = θ², the coefficient of x×(x×p) in the exponential chart.
fn exp_chart_coefficient(s: f64) -> (f64, f64, f64) {
    if s < 1.0 {
        // Series (radius 4π²): the closed form cancels catastrophically near 0.
        let (mut c, mut dc, mut d2c) = (0.0, 0.0, 0.0);
        for (n, &a) in C_SERIES.iter().enumerate().rev() {
            let n = n as f64;
            c = c * s + a;
            if n >= 1.0 {
                dc = dc * s + n * a;
            }
            if n >= 2.0 {
                d2c = d2c * s + n * (n - 1.0) * a;
            }
        }
        return (c, dc, d2c);
    }
    let th = s.sqrt();
    let (sn, cs) = (0.5 * th).sin_cos();
    let cot = cs / sn;
    let csc2 = 1.0 / (sn * sn);
    let c = 1.0 / s - cot / (2.0 * th);
    let c_th = -2.0 / (s * th) + cot / (2.0 * s) + csc2 / (4.0 * th);
    let c_thth = 6.0 / (s * s) - cot / (s * th) - csc2 / (2.0 * s) - csc2 * cot / (4.0 * th);
    (c, c_th / (2.0 * th), (c_thth - c_th / th) / (4.0 * s))
}

#[inline(always)]
fn cross<T: Scalar>(a: &[T; 3], b: &[T; 3]) -> [T; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
fn dot<T: Scalar>(a: &[T; 3], b: &[T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Chart {
    pub fn name(self) -> &'static str {
        match self {
            Chart::Cayley => "cayley",
            Chart::Exp => "exp",
        }
    }

    pub fn from_name(name: &str) -> Option<Chart> {
        match name {
            "cayley" => Some(Chart::Cayley),
            "exp" => Some(Chart::Exp),
            _ => None,
        }
    }

    /// sou(x,p) when `sign = +1`, tar(x,p) when `sign = −1`: the charts differ from each other
    /// only in the sign of the ½ x×p term.
    #[inline(always)]
    fn apply<T: Scalar>(self, x: &[T; 3], p: &[T; 3], sign: f64) -> Result<[T; 3], StepFailure> {
        let xp = cross(x, p);
        let mut out = [p[0], p[1], p[2]];
        match self {
            Chart::Cayley => {
                // p ± ½ x×p + ¼ x (x·p)
                let q = dot(x, p).scale(0.25);
                for i in 0..3 {
                    out[i] = out[i] + xp[i].scale(0.5 * sign) + x[i] * q;
                }
            }
            Chart::Exp => {
                // p ± ½ x×p + c(|x|²) x×(x×p)
                let s = dot(x, x);
                if s.value() >= EXP_CHART_MAX_ANGLE * EXP_CHART_MAX_ANGLE {
                    return Err(StepFailure::ChartSingular);
                }
                let (c, dc, d2c) = exp_chart_coefficient(s.value());
                let c = s.chain(c, dc, d2c);
                let xxp = cross(x, &xp);
                for i in 0..3 {
                    out[i] = out[i] + xp[i].scale(0.5 * sign) + c * xxp[i];
                }
            }
        }
        Ok(out)
    }

    /// Source map: the spatial momentum of the covector with chart coordinates (x, p).
    pub fn sou<T: Scalar>(self, x: &[T; 3], p: &[T; 3]) -> Result<[T; 3], StepFailure> {
        self.apply(x, p, 1.0)
    }

    /// Target map: the body momentum of the covector with chart coordinates (x, p).
    pub fn tar<T: Scalar>(self, x: &[T; 3], p: &[T; 3]) -> Result<[T; 3], StepFailure> {
        self.apply(x, p, -1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dual::Dual1;

    fn norm(a: &[f64; 3]) -> f64 {
        dot(a, a).sqrt()
    }

    #[test]
    fn units_are_the_identity() {
        let p = [0.3, -1.2, 2.0];
        for chart in [Chart::Cayley, Chart::Exp] {
            assert_eq!(chart.sou(&[0.0; 3], &p).unwrap(), p);
            assert_eq!(chart.tar(&[0.0; 3], &p).unwrap(), p);
        }
    }

    #[test]
    fn source_and_target_have_equal_norms() {
        let p = [0.3, -1.2, 2.0];
        for chart in [Chart::Cayley, Chart::Exp] {
            for x in [[0.01, 0.02, -0.03], [0.4, -0.9, 0.3], [1.5, 2.0, -2.5]] {
                let (s, t) = (chart.sou(&x, &p).unwrap(), chart.tar(&x, &p).unwrap());
                assert!(
                    (norm(&s) - norm(&t)).abs() < 1e-14 * norm(&p),
                    "{chart:?} {x:?}"
                );
            }
        }
    }

    #[test]
    fn series_and_closed_form_agree_at_the_switch() {
        let (a, da, d2a) = exp_chart_coefficient(1.0 - 1e-12);
        let (b, db, d2b) = exp_chart_coefficient(1.0 + 1e-12);
        assert!((a - b).abs() < 1e-14);
        assert!((da - db).abs() < 1e-12);
        assert!((d2a - d2b).abs() < 1e-9);
        // θ = π: c = 1/π².
        let (c, _, _) = exp_chart_coefficient(std::f64::consts::PI.powi(2));
        assert!((c - 1.0 / std::f64::consts::PI.powi(2)).abs() < 1e-15);
    }

    /// The closed-form derivative of c against the series one on either side of the switch:
    /// they are independent formulas.
    #[test]
    fn exp_chart_jacobian_matches_dual_derivative_of_components() {
        let x = [0.5, -0.4, 0.9];
        let p = [1.0, 2.0, -0.5];
        let xd = [
            Dual1::var(x[0], 0),
            Dual1::var(x[1], 1),
            Dual1::var(x[2], 2),
        ];
        let pd = p.map(Dual1::cst);
        let s = Chart::Exp.sou(&xd, &pd).unwrap();
        // Compare with a second independent evaluation: central differences on exact arithmetic
        // are not exact, so use a tight step and a loose-enough bound only as a sanity check.
        let h = 1e-6;
        for j in 0..3 {
            let mut xp = x;
            let mut xm = x;
            xp[j] += h;
            xm[j] -= h;
            let sp = Chart::Exp.sou(&xp, &p).unwrap();
            let sm = Chart::Exp.sou(&xm, &p).unwrap();
            for i in 0..3 {
                let fd = (sp[i] - sm[i]) / (2.0 * h);
                assert!((s[i].g[j] - fd).abs() < 1e-8, "d sou_{i}/d x_{j}");
            }
        }
    }

    #[test]
    fn exp_chart_refuses_the_singular_angle() {
        let x = [0.0, 0.0, 2.0 * std::f64::consts::PI];
        assert_eq!(
            Chart::Exp.sou(&x, &[1.0, 0.0, 0.0]),
            Err(StepFailure::ChartSingular)
        );
    }
}
