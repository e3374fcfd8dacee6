//! Model files: one safetensors file holding a generating function and its metadata.
//!
//! Tensors (all little-endian; float64 unless stated), for a Lie algebra of dimension N:
//! - `algebra.structure_constants` (N, N, N), c[i][j][k] with [e_i, e_j] = Σ_k c[i][j][k] e_k;
//!   optional for N = 3, where its absence means so(3) (files written before other algebras);
//! - `poly.powers` int64 (n, 1 + N), rows (k, e₁, …, e_N) for t^k p₁^e₁ ⋯ p_N^e_N, and
//!   `poly.coeffs` (n,);
//! - `mlp.{i}.weight` (out, in) and `mlp.{i}.bias` (out,), i = 0, 1, …; inputs (t, p₁, …, p_N),
//!   tanh after every layer but the last, one output.
//!
//! Metadata (strings): `format` = [`FORMAT`], `chart` (`cayley` | `exp`; cayley for so(3) only);
//! with an MLP also `mlp_power` (m ≥ 1) and `mlp_inputs` (`t,p` | `homogeneous`, see
//! [`MlpInputs`]). Other keys (system, training record, …) are kept for the caller.
//!
//! A file whose metadata says `structure` = `log_canonical` holds a generating function of the
//! log-canonical groupoid instead ([`LogModel`]); [`Model`] refuses it, and any other
//! `structure` than `lie_poisson`, by name.

use std::collections::HashMap;
use std::path::Path;

use safetensors::{Dtype, SafeTensors};

use crate::error::CoreError;
use crate::generating::{GeneratingFunction, Layer, Mlp, MlpInputs, Monomial, Polynomial};
use crate::memory::{check_fits, try_collect, try_with_capacity};
use crate::stepper::{BisectionStepper, NewtonOptions};
use crate::structures::lie_groupoid::{Chart, Groupoid, LieAlgebra};
use crate::structures::{ExpMonomial, ExpPolynomial, LearnedExp, LogCanonical};
use crate::structures::{LearnedLogBisection, LearnedLogStepper};
use crate::{with_dim, MAX_DIM};

/// The format tag every model file carries.
pub const FORMAT: &str = "poisson_rs.generating/1";

/// Largest exponent accepted in a polynomial term or as mlp_power (guards against corrupt files).
const MAX_POWER: i64 = 64;

/// Most MLP layers a file may hold; bounds allocation before any tensor is read.
const MAX_LAYERS: usize = 1024;

/// The layer index of `mlp.{i}.weight` / `mlp.{i}.bias`, with `i` written canonically.
fn layer_index(name: &str) -> Option<usize> {
    let rest = name.strip_prefix("mlp.")?;
    let digits = rest
        .strip_suffix(".weight")
        .or_else(|| rest.strip_suffix(".bias"))?;
    let canonical = !digits.is_empty()
        && digits.bytes().all(|b| b.is_ascii_digit())
        && (digits == "0" || !digits.starts_with('0'));
    canonical.then(|| digits.parse().ok()).flatten()
}

/// One polynomial term as read: (t-power, p-powers, coefficient).
type RawMonomial = (u32, Vec<u32>, f64);

/// A loaded, validated model of any dimension N ≤ [`MAX_DIM`]. [`Model::stepper`] turns it into
/// the N-dimensional (monomorphised) integrator.
#[derive(Clone, Debug)]
pub struct Model {
    /// The dimension N of the Lie algebra.
    pub dim: usize,
    pub chart: Chart,
    /// c[i][j][k] flattened row-major, N³ numbers.
    pub structure_constants: Vec<f64>,
    terms: Vec<RawMonomial>,
    pub mlp: Option<Mlp>,
    pub mlp_power: u32,
    pub inputs: MlpInputs,
    pub metadata: HashMap<String, String>,
}

/// A model file's bytes; a missing file is [`CoreError::NotFound`], any other failure
/// [`CoreError::Io`], both naming the path.
fn read_file(path: &Path) -> Result<Vec<u8>, CoreError> {
    std::fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => CoreError::NotFound(path.display().to_string()),
        _ => CoreError::Io(format!("{}: {e}", path.display())),
    })
}

fn format_err(m: impl Into<String>) -> CoreError {
    CoreError::Format(m.into())
}

/// A tensor's shape and values, `dtype` checked and each 8-byte little-endian value decoded
/// by `decode`.
fn read_tensor<T>(
    st: &SafeTensors<'_>,
    name: &str,
    dtype: Dtype,
    decode: fn([u8; 8]) -> T,
) -> Result<(Vec<usize>, Vec<T>), CoreError> {
    let t = st
        .tensor(name)
        .map_err(|e| format_err(format!("tensor {name}: {e}")))?;
    if t.dtype() != dtype {
        return Err(format_err(format!(
            "tensor {name} must be {}, found {:?}",
            if dtype == Dtype::F64 {
                "float64"
            } else {
                "int64"
            },
            t.dtype()
        )));
    }
    let data = t.data();
    let v = try_collect(
        data.len() / 8,
        data.chunks_exact(8).map(|b| {
            let mut a = [0u8; 8];
            a.copy_from_slice(b);
            decode(a)
        }),
        &format!("tensor {name}"),
    )?;
    Ok((t.shape().to_vec(), v))
}

fn read_f64(st: &SafeTensors<'_>, name: &str) -> Result<(Vec<usize>, Vec<f64>), CoreError> {
    read_tensor(st, name, Dtype::F64, f64::from_le_bytes)
}

fn read_polynomial(st: &SafeTensors<'_>) -> Result<(usize, Vec<RawMonomial>), CoreError> {
    let powers = st
        .tensor("poly.powers")
        .map_err(|e| format_err(format!("tensor poly.powers: {e}")))?;
    if powers.dtype() != Dtype::I64 {
        return Err(format_err(format!(
            "tensor poly.powers must be int64, found {:?}",
            powers.dtype()
        )));
    }
    let shape = powers.shape();
    if shape.len() != 2 || !(2..=MAX_DIM + 1).contains(&shape[1]) {
        return Err(format_err(format!(
            "tensor poly.powers must have shape (n, 1 + N) with 1 <= N <= {MAX_DIM}, found \
             {shape:?}"
        )));
    }
    let width = shape[1];
    let data = powers.data();
    let raw: Vec<i64> = try_collect(
        data.len() / 8,
        data.chunks_exact(8).map(|b| {
            let mut a = [0u8; 8];
            a.copy_from_slice(b);
            i64::from_le_bytes(a)
        }),
        "tensor poly.powers",
    )?;
    let (cshape, coeffs) = read_f64(st, "poly.coeffs")?;
    if cshape != [shape[0]] {
        return Err(format_err(format!(
            "poly.coeffs has shape {cshape:?} but poly.powers has {} rows",
            shape[0]
        )));
    }
    let mut terms = try_with_capacity(coeffs.len(), "the polynomial terms")?;
    for (row, &coeff) in raw.chunks_exact(width).zip(&coeffs) {
        if let Some(&bad) = row.iter().find(|&&e| !(0..=MAX_POWER).contains(&e)) {
            return Err(format_err(format!(
                "poly.powers holds exponent {bad}, outside 0..={MAX_POWER}"
            )));
        }
        terms.push((
            row[0] as u32,
            row[1..].iter().map(|&e| e as u32).collect(),
            coeff,
        ));
    }
    Ok((width - 1, terms))
}

/// The number of MLP layers in a model file whose other tensors are `known`: refuses any other
/// tensor name, and a file whose loading would not fit in memory (each MLP weight is held four
/// times: as read, packed, transposed and packed again), up front rather than part-way.
fn count_layers(st: &SafeTensors<'_>, known: &[&str]) -> Result<usize, CoreError> {
    let mut n_layers = 0;
    for name in st.names() {
        if known.contains(&name) {
            continue;
        }
        match layer_index(name).filter(|&i| i < MAX_LAYERS) {
            Some(i) => n_layers = n_layers.max(i + 1),
            None => return Err(format_err(format!("unexpected tensor '{name}'"))),
        }
    }
    let tensor_bytes = st
        .tensors()
        .iter()
        .map(|(_, t)| t.data().len())
        .fold(0usize, usize::saturating_add);
    check_fits(
        tensor_bytes.saturating_mul(4),
        "loading this model",
        "the model is too large for this machine",
    )?;
    Ok(n_layers)
}

/// The structure constants, if the file holds them: (N, N, N) float64.
fn read_algebra(st: &SafeTensors<'_>) -> Result<Option<(usize, Vec<f64>)>, CoreError> {
    if !st.names().contains(&"algebra.structure_constants") {
        return Ok(None);
    }
    let (shape, c) = read_f64(st, "algebra.structure_constants")?;
    match shape[..] {
        [a, b, d] if a == b && b == d && (1..=MAX_DIM).contains(&a) => Ok(Some((a, c))),
        _ => Err(format_err(format!(
            "algebra.structure_constants must have shape (N, N, N) with 1 <= N <= {MAX_DIM}, \
             found {shape:?}"
        ))),
    }
}

fn read_mlp(st: &SafeTensors<'_>, n_layers: usize) -> Result<Mlp, CoreError> {
    let mut layers = Vec::with_capacity(n_layers);
    for i in 0..n_layers {
        let (ws, w) = read_f64(st, &format!("mlp.{i}.weight"))?;
        let (bs, b) = read_f64(st, &format!("mlp.{i}.bias"))?;
        if ws.len() != 2 || bs.len() != 1 || bs[0] != ws[0] {
            return Err(format_err(format!(
                "layer {i}: weight shape {ws:?} and bias shape {bs:?} do not match (out, in) and (out,)"
            )));
        }
        layers.push(Layer::new(ws[1], ws[0], w, b)?);
    }
    Mlp::new(layers)
}

impl Model {
    /// Parses a model from the bytes of a safetensors file.
    pub fn from_bytes(bytes: &[u8]) -> Result<Model, CoreError> {
        let (_, header) = SafeTensors::read_metadata(bytes)
            .map_err(|e| format_err(format!("not a readable safetensors file ({e})")))?;
        let metadata = header
            .metadata()
            .clone()
            .ok_or_else(|| format_err("the file has no metadata; is it a poisson_rs model?"))?;
        let get = |key: &str| {
            metadata
                .get(key)
                .ok_or_else(|| format_err(format!("metadata key '{key}' is missing")))
        };
        let format = get("format")?;
        if format != FORMAT {
            return Err(format_err(format!(
                "format is '{format}', expected '{FORMAT}'"
            )));
        }
        check_structure(&metadata, LIE_POISSON)?;
        let chart_name = get("chart")?;
        let chart = Chart::from_name(chart_name)
            .ok_or_else(|| format_err(format!("unknown chart '{chart_name}' (cayley or exp)")))?;

        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| format_err(format!("not a readable safetensors file ({e})")))?;
        let n_layers = count_layers(
            &st,
            &["poly.powers", "poly.coeffs", "algebra.structure_constants"],
        )?;
        let names = st.names();
        let has_poly = names.contains(&"poly.powers") || names.contains(&"poly.coeffs");
        let algebra = read_algebra(&st)?;
        let (poly_dim, terms) = if has_poly {
            let (d, t) = read_polynomial(&st)?;
            (Some(d), t)
        } else {
            (None, Vec::new())
        };
        let mlp = if n_layers > 0 {
            Some(read_mlp(&st, n_layers)?)
        } else {
            None
        };
        if terms.is_empty() && mlp.is_none() {
            return Err(format_err(
                "the file holds neither polynomial terms nor an MLP",
            ));
        }
        // The dimension, from every tensor that states it; they must agree.
        let mlp_dim = mlp.as_ref().map(|m| m.n_inputs().saturating_sub(1));
        let algebra_dim = algebra.as_ref().map(|(d, _)| *d);
        let dim = algebra_dim.or(poly_dim).or(mlp_dim).unwrap_or(3);
        for (what, d) in [("poly.powers", poly_dim), ("the first MLP layer", mlp_dim)] {
            if let Some(d) = d.filter(|&d| d != dim) {
                return Err(format_err(format!(
                    "{what} is for dimension {d} but the model's algebra has dimension {dim}"
                )));
            }
        }
        if !(1..=MAX_DIM).contains(&dim) {
            return Err(format_err(format!(
                "dimension {dim} is outside 1..={MAX_DIM}"
            )));
        }
        let structure_constants = match algebra {
            Some((_, c)) => c,
            None if dim == 3 => so3_constants(),
            None => {
                return Err(format_err(format!(
                    "a model of dimension {dim} needs the tensor algebra.structure_constants"
                )))
            }
        };
        let mlp_power = match (&mlp, metadata.get("mlp_power")) {
            (None, _) => 0,
            (Some(_), None) => return Err(format_err("metadata key 'mlp_power' is missing")),
            (Some(_), Some(s)) => s
                .parse::<u32>()
                .ok()
                .filter(|&m| i64::from(m) <= MAX_POWER)
                .ok_or_else(|| {
                    format_err(format!(
                        "mlp_power '{s}' is not an integer in 0..={MAX_POWER}"
                    ))
                })?,
        };
        let inputs = match (&mlp, metadata.get("mlp_inputs")) {
            (None, _) => MlpInputs::Plain,
            (Some(_), None) => return Err(format_err("metadata key 'mlp_inputs' is missing")),
            (Some(_), Some(s)) => MlpInputs::from_name(s).ok_or_else(|| {
                format_err(format!("unknown mlp_inputs '{s}' (t,p or homogeneous)"))
            })?,
        };
        let model = Model {
            dim,
            chart,
            structure_constants,
            terms,
            mlp,
            mlp_power,
            inputs,
            metadata,
        };
        // Builds the typed pieces once, so every check runs at load time.
        with_dim!(dim, N => {
            model.generating::<N>()?;
            model.groupoid::<N>().map_err(|e| format_err(e.to_string()))?;
        }, unreachable_dim(dim)?);
        Ok(model)
    }

    /// Reads and parses a model file.
    pub fn from_file(path: &Path) -> Result<Model, CoreError> {
        let bytes = read_file(path)?;
        Model::from_bytes(&bytes)
    }

    /// The generating function, for dimension N = `self.dim`.
    pub fn generating<const N: usize>(&self) -> Result<GeneratingFunction<N>, CoreError> {
        self.check_dim::<N>()?;
        let terms = self
            .terms
            .iter()
            .map(|(k, e, c)| Monomial {
                t_power: *k,
                p_powers: std::array::from_fn(|i| e[i]),
                coeff: *c,
            })
            .collect();
        GeneratingFunction::new(
            Polynomial::new(terms)?,
            self.mlp.clone(),
            self.mlp_power,
            self.inputs,
        )
    }

    /// The groupoid (algebra and chart), for dimension N = `self.dim`.
    pub fn groupoid<const N: usize>(&self) -> Result<Groupoid<N>, CoreError> {
        self.check_dim::<N>()?;
        let c = &self.structure_constants;
        let algebra = LieAlgebra::new(std::array::from_fn(|i| {
            std::array::from_fn(|j| std::array::from_fn(|k| c[(i * N + j) * N + k]))
        }))?;
        Groupoid::new(algebra, self.chart)
    }

    /// The model's integrator with the given Newton settings, for dimension N = `self.dim`.
    pub fn stepper<const N: usize>(
        &self,
        newton: NewtonOptions,
    ) -> Result<BisectionStepper<N>, CoreError> {
        Ok(BisectionStepper::new(
            self.generating::<N>()?,
            self.groupoid::<N>()?,
            newton,
        ))
    }

    /// Terms of the polynomial part.
    pub fn n_polynomial_terms(&self) -> usize {
        self.terms.len()
    }

    fn check_dim<const N: usize>(&self) -> Result<(), CoreError> {
        if N != self.dim || self.structure_constants.len() != N * N * N {
            return Err(CoreError::Invalid(format!(
                "the model has dimension {}, not {N}",
                self.dim
            )));
        }
        Ok(())
    }
}

/// The Levi-Civita symbol, flattened: so(3).
fn so3_constants() -> Vec<f64> {
    let mut c = vec![0.0; 27];
    for (i, j, k) in [(0, 1, 2), (1, 2, 0), (2, 0, 1)] {
        c[(i * 3 + j) * 3 + k] = 1.0;
        c[(j * 3 + i) * 3 + k] = -1.0;
    }
    c
}

fn unreachable_dim(dim: usize) -> Result<(), CoreError> {
    Err(format_err(format!(
        "dimension {dim} is outside 1..={MAX_DIM}"
    )))
}

/// The `structure` metadata of a Lie–Poisson model file (also what a file without the key is).
pub const LIE_POISSON: &str = "lie_poisson";
/// The `structure` metadata of a log-canonical model file ([`LogModel`]).
pub const LOG_CANONICAL: &str = "log_canonical";

/// Refuses a file whose `structure` metadata is not `expected` (a file without the key is
/// Lie–Poisson), naming both.
fn check_structure(metadata: &HashMap<String, String>, expected: &str) -> Result<(), CoreError> {
    let found = metadata
        .get("structure")
        .map_or(LIE_POISSON, String::as_str);
    if found == expected {
        return Ok(());
    }
    let known = [LIE_POISSON, LOG_CANONICAL];
    Err(format_err(if known.contains(&found) {
        format!("the model's structure is '{found}', not '{expected}': load it as such")
    } else {
        format!(
            "unknown model structure '{}' (known: {})",
            found.chars().take(60).collect::<String>(),
            known.join(", ")
        )
    }))
}

/// An int64 tensor's shape and values.
fn read_i64(st: &SafeTensors<'_>, name: &str) -> Result<(Vec<usize>, Vec<i64>), CoreError> {
    read_tensor(st, name, Dtype::I64, i64::from_le_bytes)
}

/// One term c · t^k · e^{e·q} as read.
type RawExpMonomial = (u32, Vec<i32>, f64);

/// A learned generating function of a log-canonical structure π_ij = c_ij x_i x_j, in q = ln x:
/// S(t, q) = Σ coeffs · t^k e^{e·q} + t · linear·q + t^m · N(t, q).
///
/// Tensors: `structure.c` (N, N) antisymmetric; `poly.powers` int64 (M, 1 + N), rows
/// (k, e₁, …, e_N) with 0 ≤ k ≤ 64 and |e_i| ≤ 256, `poly.coeffs` (M,), `poly.linear` (N,);
/// `mlp.{i}.weight`/`.bias` as in a Lie–Poisson file, inputs (t, q₁, …, q_N). Metadata:
/// `format`, `structure` = `log_canonical`, and with an MLP `mlp_power` (≥ 1) and
/// `mlp_inputs` = `t,p`.
#[derive(Clone, Debug)]
pub struct LogModel {
    pub dim: usize,
    /// c flattened row-major, N² numbers.
    pub c: Vec<f64>,
    terms: Vec<RawExpMonomial>,
    pub linear: Vec<f64>,
    pub mlp: Option<Mlp>,
    pub mlp_power: u32,
    pub metadata: HashMap<String, String>,
}

impl LogModel {
    /// Parses a log-canonical model from the bytes of a safetensors file.
    pub fn from_bytes(bytes: &[u8]) -> Result<LogModel, CoreError> {
        let (_, header) = SafeTensors::read_metadata(bytes)
            .map_err(|e| format_err(format!("not a readable safetensors file ({e})")))?;
        let metadata = header
            .metadata()
            .clone()
            .ok_or_else(|| format_err("the file has no metadata; is it a poisson_rs model?"))?;
        let format = metadata
            .get("format")
            .ok_or_else(|| format_err("metadata key 'format' is missing"))?;
        if format != FORMAT {
            return Err(format_err(format!(
                "format is '{format}', expected '{FORMAT}'"
            )));
        }
        if !metadata.contains_key("structure") {
            return Err(format_err(format!(
                "metadata key 'structure' is missing (a log-canonical model says \
                 '{LOG_CANONICAL}')"
            )));
        }
        check_structure(&metadata, LOG_CANONICAL)?;
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| format_err(format!("not a readable safetensors file ({e})")))?;
        let n_layers = count_layers(
            &st,
            &["structure.c", "poly.powers", "poly.coeffs", "poly.linear"],
        )?;
        let (cshape, c) = read_f64(&st, "structure.c")?;
        let dim = match cshape[..] {
            [a, b] if a == b && (1..=MAX_DIM).contains(&a) => a,
            _ => {
                return Err(format_err(format!(
                    "structure.c must have shape (N, N) with 1 <= N <= {MAX_DIM}, found \
                     {cshape:?}"
                )))
            }
        };
        let (lshape, linear) = read_f64(&st, "poly.linear")?;
        if lshape != [dim] {
            return Err(format_err(format!(
                "poly.linear must have shape ({dim},), found {lshape:?}"
            )));
        }
        let (pshape, powers) = read_i64(&st, "poly.powers")?;
        let (cs, coeffs) = read_f64(&st, "poly.coeffs")?;
        if pshape.len() != 2 || pshape[1] != dim + 1 || cs != [pshape[0]] {
            return Err(format_err(format!(
                "poly.powers must have shape (M, {}) and poly.coeffs (M,), found {pshape:?} and \
                 {cs:?}",
                dim + 1
            )));
        }
        let mut terms = try_with_capacity(coeffs.len(), "the polynomial terms")?;
        for (row, &coeff) in powers.chunks_exact(dim + 1).zip(&coeffs) {
            let t_power = u32::try_from(row[0])
                .ok()
                .filter(|&k| i64::from(k) <= MAX_POWER)
                .ok_or_else(|| {
                    format_err(format!(
                        "poly.powers holds t-power {}, outside 0..={MAX_POWER}",
                        row[0]
                    ))
                })?;
            let max_e = i64::from(crate::structures::log_canonical::MAX_EXPONENT);
            if let Some(&bad) = row[1..].iter().find(|&&e| !(-max_e..=max_e).contains(&e)) {
                return Err(format_err(format!(
                    "poly.powers holds exponent {bad}, outside -{max_e}..={max_e}"
                )));
            }
            terms.push((t_power, row[1..].iter().map(|&e| e as i32).collect(), coeff));
        }
        let mlp = if n_layers > 0 {
            Some(read_mlp(&st, n_layers)?)
        } else {
            None
        };
        let mlp_power = match (&mlp, metadata.get("mlp_power")) {
            (None, _) => 0,
            (Some(_), None) => return Err(format_err("metadata key 'mlp_power' is missing")),
            (Some(_), Some(s)) => s
                .parse::<u32>()
                .ok()
                .filter(|&m| (1..=MAX_POWER).contains(&i64::from(m)))
                .ok_or_else(|| {
                    format_err(format!(
                        "mlp_power '{s}' is not an integer in 1..={MAX_POWER}"
                    ))
                })?,
        };
        if mlp.is_some() {
            match metadata.get("mlp_inputs").map(String::as_str) {
                Some("t,p") => {}
                Some(s) => {
                    return Err(format_err(format!(
                        "mlp_inputs '{s}' is not supported by a log-canonical model (t,p)"
                    )))
                }
                None => return Err(format_err("metadata key 'mlp_inputs' is missing")),
            }
        }
        let model = LogModel {
            dim,
            c,
            terms,
            linear,
            mlp,
            mlp_power,
            metadata,
        };
        with_dim!(dim, N => {
            model.generating::<N>()?;
            model.structure::<N>().map_err(|e| format_err(e.to_string()))?;
        }, unreachable_dim(dim)?);
        Ok(model)
    }

    /// Reads and parses a log-canonical model file.
    pub fn from_file(path: &Path) -> Result<LogModel, CoreError> {
        let bytes = read_file(path)?;
        LogModel::from_bytes(&bytes)
    }

    fn check_dim<const N: usize>(&self) -> Result<(), CoreError> {
        if N != self.dim || self.c.len() != N * N || self.linear.len() != N {
            return Err(CoreError::Invalid(format!(
                "the model has dimension {}, not {N}",
                self.dim
            )));
        }
        Ok(())
    }

    /// The structure c, for dimension N = `self.dim`.
    pub fn structure<const N: usize>(&self) -> Result<LogCanonical<N>, CoreError> {
        self.check_dim::<N>()?;
        LogCanonical::new(std::array::from_fn(|i| {
            std::array::from_fn(|j| self.c[i * N + j])
        }))
    }

    /// The generating function, for dimension N = `self.dim`.
    pub fn generating<const N: usize>(&self) -> Result<LearnedExp<N>, CoreError> {
        self.check_dim::<N>()?;
        let mut terms = try_with_capacity(self.terms.len(), "the polynomial terms")?;
        terms.extend(self.terms.iter().map(|(k, e, c)| ExpMonomial {
            t_power: *k,
            exponents: std::array::from_fn(|i| e[i]),
            coeff: *c,
        }));
        let taylor = ExpPolynomial::new(terms, std::array::from_fn(|i| self.linear[i]))
            .map_err(|e| format_err(e.to_string()))?;
        let network = GeneratingFunction::new(
            Polynomial::default(),
            self.mlp.clone(),
            self.mlp_power,
            MlpInputs::Plain,
        )?;
        LearnedExp::new(taylor, network)
    }

    /// The model's integrator in q = ln x (Newton stops once |δ|∞ ≤ tol · max(|q|∞, 1); a step
    /// whose e^q leaves the float64 orthant fails), for dimension N = `self.dim`.
    pub fn stepper<const N: usize>(
        &self,
        newton: NewtonOptions,
    ) -> Result<LearnedLogStepper<N>, CoreError> {
        Ok(LearnedLogStepper(LearnedLogBisection::unit_scale(
            self.generating::<N>()?,
            self.structure::<N>()?,
            newton,
        )))
    }

    /// Terms of the exponential-polynomial (Taylor) part.
    pub fn n_taylor_terms(&self) -> usize {
        self.terms.len()
    }
}
