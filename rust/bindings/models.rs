//! The learned-model classes: a Lie–Poisson model file ([`PyModel`]), and a learned S on any
//! other realization ([`PyLearnedModel`]: log-canonical, polynomial bivector).

use std::path::PathBuf;

use numpy::ndarray::{Array1, Array2, Array3, Ix1, Ix2, Ix3};
use numpy::{IntoPyArray, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyMemoryError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::polynomial::{component_polynomials, polynomial, term_table};
use super::rollout::run_rollout;
use super::{check_output_bytes, detached, dim_error, finite_states, rows_match, states, Array};

use crate::generating::{Layer, Mlp, Workspace};
use crate::memory::try_with_capacity;
use crate::model::{LogModel, Model};
use crate::realization::batch_size;
use crate::realization::Generating;
use crate::rollout::PerStep;
use crate::stepper::NewtonOptions;
use crate::structures::LearnedPolynomialModel;
use crate::with_dim;

/// A generating function loaded from a model file.
#[pyclass(name = "Model", module = "poisson_rs._core", frozen)]
pub(super) struct PyModel {
    inner: Model,
}

#[pymethods]
impl PyModel {
    /// Loads a model file. Raises FileNotFoundError or ValueError.
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = detached(py, || Model::from_file(&path))?;
        Ok(PyModel { inner })
    }

    /// Parses the bytes of a model file. Raises ValueError.
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<Self> {
        let inner = detached(py, || Model::from_bytes(data))?;
        Ok(PyModel { inner })
    }

    /// The dimension N of the model's Lie algebra (3 for the rigid body).
    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim
    }

    /// The structure constants c[i, j, k] of the model's algebra, shape (N, N, N).
    #[getter]
    fn structure_constants<'py>(&self, py: Python<'py>) -> PyResult<Array<'py, Ix3>> {
        let n = self.inner.dim;
        Array3::from_shape_vec((n, n, n), self.inner.structure_constants.clone())
            .map(|a| a.into_pyarray(py))
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))
    }

    /// The file's metadata, as strings.
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.inner.metadata {
            d.set_item(k, v)?;
        }
        Ok(d)
    }

    #[getter]
    fn chart(&self) -> &'static str {
        self.inner.chart.name()
    }

    #[getter]
    fn mlp_power(&self) -> u32 {
        self.inner.mlp_power
    }

    /// Hidden layer widths of the MLP (empty without one).
    #[getter]
    fn widths(&self) -> Vec<usize> {
        self.inner.mlp.as_ref().map_or_else(Vec::new, |m| {
            m.layers[..m.layers.len() - 1]
                .iter()
                .map(|l| l.n_out)
                .collect()
        })
    }

    #[getter]
    fn n_parameters(&self) -> usize {
        self.inner.mlp.as_ref().map_or(0, |m| m.n_parameters())
    }

    /// Trajectories a rollout solves together in batched passes (1: one at a time).
    #[getter]
    fn batch(&self) -> usize {
        batch_size(self.inner.mlp.as_ref())
    }

    #[getter]
    fn n_polynomial_terms(&self) -> usize {
        self.inner.n_polynomial_terms()
    }

    /// S, ∂S/∂p and ∂²S/∂p² at time t for p of shape (n, N): arrays (n,), (n, N), (n, N, N).
    fn derivatives<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
        with_dim!(self.inner.dim, N => {
            let p = states::<N>(&p, "p")?;
            let g = self.inner.generating::<N>()?;
            jets_at(py, &g, &g, t, &p)
        }, Err(dim_error(self.inner.dim)))
    }

    /// S and ∂S/∂t at (t, p) for p of shape (n, N): arrays (n,), (n,).
    fn time_derivative<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix1>)> {
        with_dim!(self.inner.dim, N => self.time_derivative_n::<N>(py, t, p), Err(dim_error(self.inner.dim)))
    }

    fn __repr__(&self) -> String {
        format!(
            "Model(dim={}, chart={:?}, polynomial_terms={}, mlp_parameters={}, mlp_power={})",
            self.inner.dim,
            self.inner.chart.name(),
            self.n_polynomial_terms(),
            self.n_parameters(),
            self.inner.mlp_power
        )
    }
}

impl PyModel {
    fn time_derivative_n<'py, const N: usize>(
        &self,
        py: Python<'py>,
        t: f64,
        p: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix1>)> {
        let p = states::<N>(&p, "p")?;
        let g = self.inner.generating::<N>()?;
        check_output_bytes(p.len().saturating_mul(2), Workspace::bytes(&g))?;
        let (s, dt) = detached(py, || {
            let mut ws = g.try_workspace()?;
            let mut s = try_with_capacity(p.len(), "the output S")?;
            let mut dt = try_with_capacity(p.len(), "the output dS/dt")?;
            for q in &p {
                let (v, d) = g.value_and_time_derivative(t, q, &mut ws);
                s.push(v);
                dt.push(d);
            }
            Ok((s, dt))
        })?;
        Ok((
            Array1::from_vec(s).into_pyarray(py),
            Array1::from_vec(dt).into_pyarray(py),
        ))
    }
}

/// Rolls out the bisection integrator of `model` from each row of `mu0` (n, N). `simplified`
/// lets batched steps reuse the Newton Jacobian (see `NewtonOptions::simplified`).
///
/// Returns the trajectories (n, n_steps // every + 1, N) and a dict of per-trajectory arrays.
/// Ctrl-C interrupts it (KeyboardInterrupt) within about SEGMENT_SECONDS.
#[pyfunction]
#[pyo3(signature = (model, mu0, h, n_steps, every=1, tol=1e-12, max_iter=50, simplified=true))]
#[allow(clippy::too_many_arguments)]
pub(super) fn rollout_model<'py>(
    py: Python<'py>,
    model: &PyModel,
    mu0: PyReadonlyArray2<'py, f64>,
    h: f64,
    n_steps: usize,
    every: usize,
    tol: f64,
    max_iter: u32,
    simplified: bool,
) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
    let newton = NewtonOptions {
        simplified,
        ..NewtonOptions::validated(tol, max_iter)?
    };
    with_dim!(model.inner.dim, N => {
        let mu0 = states::<N>(&mu0, "mu0")?;
        let stepper = model.inner.stepper::<N>(newton)?;
        run_rollout(py, &PerStep(&stepper), &mu0, h, n_steps, every, None)
    }, Err(dim_error(model.inner.dim)))
}

/// S, ∇S and ∇²S at time t for each of `x`, for any S whose network part is `network` (its
/// workspace and the outputs counted, then allocated fallibly, before the GIL is released: a
/// refusal is MemoryError, never an abort): arrays (n,), (n, N), (n, N, N).
pub(super) fn jets_at<'py, const N: usize, G: Generating<N, Workspace = Workspace<N>>>(
    py: Python<'py>,
    g: &G,
    network: &crate::generating::GeneratingFunction<N>,
    t: f64,
    x: &[[f64; N]],
) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
    let n = x.len();
    check_output_bytes(n.saturating_mul(1 + N + N * N), Workspace::bytes(network))?;
    let (s, grad, hess) = detached(py, || {
        let mut ws = network.try_workspace()?;
        let (mut s, mut grad, mut hess) = (
            try_with_capacity(n, "the output S")?,
            try_with_capacity(N * n, "the output dS/dx")?,
            try_with_capacity(N * N * n, "the output d2S/dx2")?,
        );
        for xi in x {
            let jet = g.jet(t, xi, &mut ws);
            s.push(jet.v);
            grad.extend(jet.grad());
            hess.extend(jet.hess().iter().flatten());
        }
        Ok((s, grad, hess))
    })?;
    let shape_err = |e: numpy::ndarray::ShapeError| PyRuntimeError::new_err(e.to_string());
    Ok((
        Array1::from_vec(s).into_pyarray(py),
        Array2::from_shape_vec((n, N), grad)
            .map_err(shape_err)?
            .into_pyarray(py),
        Array3::from_shape_vec((n, N, N), hess)
            .map_err(shape_err)?
            .into_pyarray(py),
    ))
}

/// The learned models one [`PyLearnedModel`] holds: a learned S on a realization, one variant
/// per realization. Each model type has the same surface (`dim`, `mlp`, `mlp_power`,
/// `generating::<N>()`, `stepper::<N>(newton)`), which [`each_model`] dispatches on.
enum Learned {
    /// On the exact log-canonical groupoid, in q = ln x, read from a model file.
    LogCanonical(LogModel),
    /// On the order-n realization of a polynomial bivector, built from its term tables.
    Polynomial(LearnedPolynomialModel),
}

/// Runs `$body` with `$m` bound to the model inside a [`Learned`], whatever its variant.
macro_rules! each_model {
    ($learned:expr, $m:ident => $body:expr) => {
        match $learned {
            Learned::LogCanonical($m) => $body,
            Learned::Polynomial($m) => $body,
        }
    };
}

/// A learned generating function S(t, x) = exact Taylor-HJ terms + t^m · MLP(t, x) on a
/// realization, stepped by full Newton on tar(∇S(h, x), x) = x_k, then x_{k+1} from sou
/// (|δ|∞ ≤ tol · max(|x|∞, 1)). One class for every realization: the log-canonical groupoid
/// (x is q = ln x there, every monomial Casimir kept to round-off whatever the network learned)
/// and the order-n realization of a polynomial bivector.
#[pyclass(name = "LearnedModel", module = "poisson_rs._core", frozen)]
pub(super) struct PyLearnedModel {
    inner: Learned,
    /// The model file's metadata (empty for a model built from tables).
    metadata: Vec<(String, String)>,
}

#[pymethods]
impl PyLearnedModel {
    /// Parses the bytes of a log-canonical model file (metadata `structure = log_canonical`).
    /// Raises ValueError.
    #[staticmethod]
    fn from_log_canonical_bytes(py: Python<'_>, data: &[u8]) -> PyResult<Self> {
        let inner = detached(py, || LogModel::from_bytes(data))?;
        let mut metadata: Vec<(String, String)> = inner
            .metadata
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        metadata.sort();
        Ok(PyLearnedModel {
            inner: Learned::LogCanonical(inner),
            metadata,
        })
    }

    /// A learned S on the order-n realization of a polynomial bivector: β (sou) and α (tar) as
    /// term tables over (p, x) as for `rollout_polynomial_realization`, the Taylor part as a
    /// term table over (t, x), the MLP's layers (`weights[i]` (out, in), `biases[i]` (out,),
    /// inputs (t, x), tanh after every layer but the last, one output; empty lists: no
    /// network). Raises ValueError for a malformed table or network.
    #[staticmethod]
    #[pyo3(signature = (sou_index, sou_coeffs, sou_exponents, tar_index, tar_coeffs, tar_exponents, s_coeffs, s_exponents, weights, biases, mlp_power))]
    #[allow(clippy::too_many_arguments)]
    fn from_polynomial_tables(
        sou_index: PyReadonlyArray1<'_, i64>,
        sou_coeffs: PyReadonlyArray1<'_, f64>,
        sou_exponents: PyReadonlyArray2<'_, i64>,
        tar_index: PyReadonlyArray1<'_, i64>,
        tar_coeffs: PyReadonlyArray1<'_, f64>,
        tar_exponents: PyReadonlyArray2<'_, i64>,
        s_coeffs: PyReadonlyArray1<'_, f64>,
        s_exponents: PyReadonlyArray2<'_, i64>,
        weights: Vec<PyReadonlyArray2<'_, f64>>,
        biases: Vec<PyReadonlyArray1<'_, f64>>,
        mlp_power: u32,
    ) -> PyResult<Self> {
        let dim = s_exponents.shape()[1].saturating_sub(1);
        let mlp = mlp_of(&weights, &biases)?;
        let inner = with_dim!(dim, N => {
            let sou = component_polynomials::<N>("sou", &sou_index, &sou_coeffs, &sou_exponents, 2 * N)?;
            let tar = component_polynomials::<N>("tar", &tar_index, &tar_coeffs, &tar_exponents, 2 * N)?;
            let (co, ex) = term_table("S", &s_coeffs, &s_exponents, N + 1)?;
            let all: Vec<usize> = (0..co.len()).collect();
            let s = polynomial("S", &co, &ex, &all, N + 1)?;
            LearnedPolynomialModel::new(N, sou, tar, s, mlp, mlp_power)?
        }, return Err(dim_error(dim)));
        Ok(PyLearnedModel {
            inner: Learned::Polynomial(inner),
            metadata: Vec::new(),
        })
    }

    /// The realization: "log_canonical" or "polynomial".
    #[getter]
    fn realization(&self) -> &'static str {
        match self.inner {
            Learned::LogCanonical(_) => "log_canonical",
            Learned::Polynomial(_) => "polynomial",
        }
    }

    /// The dimension N.
    #[getter]
    fn dim(&self) -> usize {
        each_model!(&self.inner, m => m.dim)
    }

    /// The model file's metadata, as strings (empty for a model built from tables).
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.metadata {
            d.set_item(k, v)?;
        }
        Ok(d)
    }

    #[getter]
    fn mlp_power(&self) -> u32 {
        each_model!(&self.inner, m => m.mlp_power)
    }

    #[getter]
    fn n_parameters(&self) -> usize {
        each_model!(&self.inner, m => m.mlp.as_ref().map_or(0, |n| n.n_parameters()))
    }

    /// Terms of the exact Taylor part.
    #[getter]
    fn n_taylor_terms(&self) -> usize {
        each_model!(&self.inner, m => m.n_taylor_terms())
    }

    /// S, ∂S/∂x and ∂²S/∂x² at time t for x of shape (n, N), in the realization's base
    /// coordinates: arrays (n,), (n, N), (n, N, N).
    fn derivatives<'py>(
        &self,
        py: Python<'py>,
        t: f64,
        x: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Array<'py, Ix1>, Array<'py, Ix2>, Array<'py, Ix3>)> {
        let dim = self.dim();
        each_model!(&self.inner, m => with_dim!(dim, N => {
            let x = states::<N>(&x, "x")?;
            let g = m.generating::<N>()?;
            jets_at(py, &g, &g.network, t, &x)
        }, Err(dim_error(dim))))
    }

    /// Rolls out the model's bisection integrator from each row of `x0` (n, N), finite, in the
    /// realization's base coordinates. Returns the trajectories (n, n_steps // every + 1, N)
    /// and a dict of per-trajectory arrays. A step that leaves the float64 range fails (its
    /// code in the dict). Ctrl-C interrupts it (KeyboardInterrupt).
    #[pyo3(signature = (x0, h, n_steps, every=1, tol=1e-12, max_iter=50))]
    #[allow(clippy::too_many_arguments)]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        x0: PyReadonlyArray2<'py, f64>,
        h: f64,
        n_steps: usize,
        every: usize,
        tol: f64,
        max_iter: u32,
    ) -> PyResult<(Array<'py, Ix3>, Bound<'py, PyDict>)> {
        let newton = NewtonOptions::validated(tol, max_iter)?;
        let dim = self.dim();
        each_model!(&self.inner, m => with_dim!(dim, N => {
            let stepper = m.stepper::<N>(newton)?;
            let x0 = finite_states::<N>(&x0, "x0")?;
            run_rollout(py, &PerStep(&stepper), &x0, h, n_steps, every, None)
        }, Err(dim_error(dim))))
    }

    fn __repr__(&self) -> String {
        format!(
            "LearnedModel(realization={:?}, dim={}, taylor_terms={}, mlp_parameters={}, \
             mlp_power={})",
            self.realization(),
            self.dim(),
            self.n_taylor_terms(),
            self.n_parameters(),
            self.mlp_power()
        )
    }
}

/// The MLP of `weights[i]` (out, in) and `biases[i]` (out,); None for empty lists.
fn mlp_of(
    weights: &[PyReadonlyArray2<'_, f64>],
    biases: &[PyReadonlyArray1<'_, f64>],
) -> PyResult<Option<Mlp>> {
    rows_match("biases", biases.len(), weights.len())?;
    let mut layers = Vec::new();
    layers
        .try_reserve_exact(weights.len())
        .map_err(|_| PyMemoryError::new_err("too many layers"))?;
    for (i, (w, b)) in weights.iter().zip(biases).enumerate() {
        let (ws, bs) = (w.shape(), b.shape());
        if bs[0] != ws[0] {
            return Err(PyValueError::new_err(format!(
                "layer {i}: weight shape {ws:?} and bias shape {bs:?} do not match (out, in) \
                 and (out,)"
            )));
        }
        let wv: Vec<f64> = w.as_array().iter().copied().collect();
        let bv: Vec<f64> = b.as_array().iter().copied().collect();
        layers.push(Layer::new(ws[1], ws[0], wv, bv)?);
    }
    Ok(if layers.is_empty() {
        None
    } else {
        Some(Mlp::new(layers)?)
    })
}
