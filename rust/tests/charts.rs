//! The so(3) charts against independent matrix forms.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use super::*;

type M3 = [[f64; 3]; 3];

fn hat(v: &[f64; 3]) -> M3 {
    [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]
}

fn matmul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// dexpinv(x) = I − ½ x̂ + c(θ) x̂², c = (1 − (θ/2) cot(θ/2)) / θ², closed form only.
fn dexpinv(x: &[f64; 3]) -> M3 {
    let th = norm(x);
    let c = (1.0 - 0.5 * th / (0.5 * th).tan()) / (th * th);
    let xh = hat(x);
    let xh2 = matmul(&xh, &xh);
    std::array::from_fn(|i| {
        std::array::from_fn(|j| (if i == j { 1.0 } else { 0.0 }) - 0.5 * xh[i][j] + c * xh2[i][j])
    })
}

/// Mᵀ p.
fn transpose_apply(m: &M3, p: &[f64; 3]) -> [f64; 3] {
    std::array::from_fn(|j| (0..3).map(|i| m[i][j] * p[i]).sum())
}

#[test]
fn exp_chart_matches_dexpinv_matrix_form() {
    let mut rng = Rng::new(0x5EED_0080);
    let mut radii: Vec<f64> = vec![
        0.05,
        0.1001,
        0.5,
        0.999,
        1.0,
        1.001,
        std::f64::consts::PI,
        6.0,
    ];
    for _ in 0..10 {
        radii.push(rng.range(0.1, 1.0));
        radii.push(rng.range(1.0, 6.0));
    }
    for &r in &radii {
        let x = rng.sphere(r);
        let p = rng.vec3(-3.0, 3.0);
        let sou_ref = transpose_apply(&dexpinv(&x), &p);
        let tar_ref = transpose_apply(&dexpinv(&x.map(|v| -v)), &p);
        let sou = Chart::Exp.sou(&x, &p).unwrap();
        let tar = Chart::Exp.tar(&x, &p).unwrap();
        // The closed form for c loses ~eps/θ² relative near 0, but its term is θ² small, so the
        // sizes of the terms set the scale.
        let scale = norm(&p) * (1.0 + r * r * (1.0 + 1.0 / (2.0 * std::f64::consts::PI - r)));
        let tol = 1e-14 * scale;
        let (es, et) = (norm(&sub(&sou, &sou_ref)), norm(&sub(&tar, &tar_ref)));
        assert!(
            es <= tol,
            "|x| = {r}: sou {sou:?} vs {sou_ref:?} (error {es:e}, tol {tol:e})"
        );
        assert!(
            et <= tol,
            "|x| = {r}: tar {tar:?} vs {tar_ref:?} (error {et:e}, tol {tol:e})"
        );
        // |sou| = |tar| (both are rotations of one another).
        assert!((norm(&sou) - norm(&tar)).abs() <= 1e-14 * scale);
    }
    // Near the identity the chart is p ± ½ x×p + x×(x×p)/12 to third order.
    let x = [1e-5, -2e-5, 3e-5];
    let p = [1.0, 2.0, 3.0];
    let xp = cross(&x, &p);
    let xxp = cross(&x, &xp);
    let approx: [f64; 3] = std::array::from_fn(|i| p[i] + 0.5 * xp[i] + xxp[i] / 12.0);
    let sou = Chart::Exp.sou(&x, &p).unwrap();
    assert!(norm(&sub(&sou, &approx)) < 1e-15 * norm(&p));
    // Beyond the guard the chart reports itself singular.
    let x = [0.0, 6.25, 0.0];
    assert_eq!(Chart::Exp.sou(&x, &p), Err(StepFailure::ChartSingular));
    assert_eq!(Chart::Exp.tar(&x, &p), Err(StepFailure::ChartSingular));
}

/// The Cayley chart against its formula written as a matrix: sou = (I + ½ x̂ + ¼ x xᵀ) p.
#[test]
fn cayley_chart_matches_matrix_form() {
    let mut rng = Rng::new(0x5EED_0081);
    for _ in 0..50 {
        let x = rng.vec3(-3.0, 3.0);
        let p = rng.vec3(-3.0, 3.0);
        let xh = hat(&x);
        for sign in [1.0, -1.0] {
            let m: M3 = std::array::from_fn(|i| {
                std::array::from_fn(|j| {
                    (if i == j { 1.0 } else { 0.0 }) + 0.5 * sign * xh[i][j] + 0.25 * x[i] * x[j]
                })
            });
            let want: [f64; 3] = std::array::from_fn(|i| (0..3).map(|j| m[i][j] * p[j]).sum());
            let got = if sign > 0.0 {
                Chart::Cayley.sou(&x, &p).unwrap()
            } else {
                Chart::Cayley.tar(&x, &p).unwrap()
            };
            assert!(norm(&sub(&got, &want)) < 1e-13 * (1.0 + norm(&x)).powi(2) * norm(&p));
        }
    }
}

/// Newton's start on so(3): p₀ = 2μ − tar(x₀, μ) in the Cayley chart (tar's quadratic term
/// included), μ + ½ x₀ × μ in the exponential one (tar's linear part), and none where
/// |x₀|² > 1.
#[test]
fn so3_predictor_is_the_chart_at_x0() {
    use crate::realization::Realization;
    let mut rng = Rng::new(0x5EED_0082);
    for _ in 0..50 {
        let x = rng.vec3(-0.5, 0.5);
        let mu = rng.vec3(-3.0, 3.0);
        let cayley = Groupoid::so3(Chart::Cayley).unwrap();
        let got = cayley.predict(&x, &mu).unwrap();
        let t = Chart::Cayley.tar(&x, &mu).unwrap();
        let want: [f64; 3] = std::array::from_fn(|i| 2.0 * mu[i] - t[i]);
        assert!(
            norm(&sub(&got, &want)) < 1e-14 * norm(&mu),
            "{got:?} {want:?}"
        );
        let exp = Groupoid::so3(Chart::Exp).unwrap();
        let got = exp.predict(&x, &mu).unwrap();
        let turn = [
            x[1] * mu[2] - x[2] * mu[1],
            x[2] * mu[0] - x[0] * mu[2],
            x[0] * mu[1] - x[1] * mu[0],
        ];
        let want: [f64; 3] = std::array::from_fn(|i| mu[i] + 0.5 * turn[i]);
        assert!(
            norm(&sub(&got, &want)) < 1e-14 * norm(&mu),
            "{got:?} {want:?}"
        );
    }
    let far = [1.0, 0.5, 0.1];
    assert!(Groupoid::so3(Chart::Cayley)
        .unwrap()
        .predict(&far, &[1.0, 2.0, 3.0])
        .is_none());
}
