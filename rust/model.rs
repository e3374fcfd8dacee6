//! Model files: one safetensors file holding a generating function and its metadata.
//!
//! Tensors (all little-endian; float64 unless stated):
//! - `poly.powers` int64 (n, 4), rows (k, a, b, c) for t^k p₁^a p₂^b p₃^c, and `poly.coeffs` (n,);
//! - `mlp.{i}.weight` (out, in) and `mlp.{i}.bias` (out,), i = 0, 1, …; inputs (t, p₁, p₂, p₃),
//!   tanh after every layer but the last, one output.
//!
//! Metadata (strings): `format` = [`FORMAT`], `chart` (`cayley` | `exp`); with an MLP also
//! `mlp_power` (m ≥ 1) and `mlp_inputs` (`t,p` | `homogeneous`, see [`MlpInputs`]). Other keys (system, inertia, training record, …) are kept for the caller.

use std::collections::HashMap;
use std::path::Path;

use safetensors::{Dtype, SafeTensors};

use crate::error::CoreError;
use crate::generating::{GeneratingFunction, Layer, Mlp, MlpInputs, Monomial, Polynomial};
use crate::groupoid::Chart;
use crate::stepper::{BisectionStepper, NewtonOptions};

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

/// A loaded model: its generating function, chart and metadata.
#[derive(Clone, Debug)]
pub struct Model {
    pub generating: GeneratingFunction,
    pub chart: Chart,
    pub metadata: HashMap<String, String>,
}

fn format_err(m: impl Into<String>) -> CoreError {
    CoreError::Format(m.into())
}

fn read_f64(st: &SafeTensors<'_>, name: &str) -> Result<(Vec<usize>, Vec<f64>), CoreError> {
    let t = st
        .tensor(name)
        .map_err(|e| format_err(format!("tensor {name}: {e}")))?;
    if t.dtype() != Dtype::F64 {
        return Err(format_err(format!(
            "tensor {name} must be float64, found {:?}",
            t.dtype()
        )));
    }
    let v = t
        .data()
        .chunks_exact(8)
        .map(|b| {
            let mut a = [0u8; 8];
            a.copy_from_slice(b);
            f64::from_le_bytes(a)
        })
        .collect();
    Ok((t.shape().to_vec(), v))
}

fn read_polynomial(st: &SafeTensors<'_>) -> Result<Polynomial, CoreError> {
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
    if shape.len() != 2 || shape[1] != 4 {
        return Err(format_err(format!(
            "tensor poly.powers must have shape (n, 4), found {shape:?}"
        )));
    }
    let raw: Vec<i64> = powers
        .data()
        .chunks_exact(8)
        .map(|b| {
            let mut a = [0u8; 8];
            a.copy_from_slice(b);
            i64::from_le_bytes(a)
        })
        .collect();
    let (cshape, coeffs) = read_f64(st, "poly.coeffs")?;
    if cshape != [shape[0]] {
        return Err(format_err(format!(
            "poly.coeffs has shape {cshape:?} but poly.powers has {} rows",
            shape[0]
        )));
    }
    let mut terms = Vec::with_capacity(coeffs.len());
    for (row, &coeff) in raw.chunks_exact(4).zip(&coeffs) {
        if let Some(&bad) = row.iter().find(|&&e| !(0..=MAX_POWER).contains(&e)) {
            return Err(format_err(format!(
                "poly.powers holds exponent {bad}, outside 0..={MAX_POWER}"
            )));
        }
        terms.push(Monomial {
            t_power: row[0] as u32,
            p_powers: [row[1] as u32, row[2] as u32, row[3] as u32],
            coeff,
        });
    }
    Ok(Polynomial { terms })
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
        let chart_name = get("chart")?;
        let chart = Chart::from_name(chart_name)
            .ok_or_else(|| format_err(format!("unknown chart '{chart_name}' (cayley or exp)")))?;

        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| format_err(format!("not a readable safetensors file ({e})")))?;
        let mut n_layers = 0;
        let mut has_poly = false;
        for name in st.names() {
            if name == "poly.powers" || name == "poly.coeffs" {
                has_poly = true;
            } else if let Some(i) = layer_index(name).filter(|&i| i < MAX_LAYERS) {
                n_layers = n_layers.max(i + 1);
            } else {
                return Err(format_err(format!("unexpected tensor '{name}'")));
            }
        }
        let polynomial = if has_poly {
            read_polynomial(&st)?
        } else {
            Polynomial::default()
        };
        let mlp = if n_layers > 0 {
            Some(read_mlp(&st, n_layers)?)
        } else {
            None
        };
        if polynomial.terms.is_empty() && mlp.is_none() {
            return Err(format_err(
                "the file holds neither polynomial terms nor an MLP",
            ));
        }
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
        let generating = GeneratingFunction::new(polynomial, mlp, mlp_power, inputs)?;
        Ok(Model {
            generating,
            chart,
            metadata,
        })
    }

    /// Reads and parses a model file.
    pub fn from_file(path: &Path) -> Result<Model, CoreError> {
        let bytes = std::fs::read(path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => CoreError::NotFound(path.display().to_string()),
            _ => CoreError::Io(format!("{}: {e}", path.display())),
        })?;
        Model::from_bytes(&bytes)
    }

    /// The model's integrator with the given Newton settings.
    pub fn stepper(&self, newton: NewtonOptions) -> BisectionStepper {
        BisectionStepper {
            generating: self.generating.clone(),
            chart: self.chart,
            newton,
        }
    }
}
