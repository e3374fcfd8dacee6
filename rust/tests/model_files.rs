//! Model files: round trips, corrupt and hostile files, and a fuzzer of the loader.

// Index loops over 3-vectors and 3×3 matrices read more clearly as the formulas they test.
#![allow(clippy::needless_range_loop)]

use super::*;

/// An owned tensor to serialise.
#[derive(Clone)]
struct Tensor {
    name: String,
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

fn f64_tensor(name: &str, shape: &[usize], values: &[f64]) -> Tensor {
    Tensor {
        name: name.into(),
        dtype: Dtype::F64,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn i64_tensor(name: &str, shape: &[usize], values: &[i64]) -> Tensor {
    Tensor {
        name: name.into(),
        dtype: Dtype::I64,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn f32_tensor(name: &str, shape: &[usize], values: &[f32]) -> Tensor {
    Tensor {
        name: name.into(),
        dtype: Dtype::F32,
        shape: shape.to_vec(),
        data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn serialize_tensors(tensors: &[Tensor], metadata: Option<HashMap<String, String>>) -> Vec<u8> {
    let views: Vec<(String, TensorView<'_>)> = tensors
        .iter()
        .map(|t| {
            (
                t.name.clone(),
                TensorView::new(t.dtype, t.shape.clone(), &t.data).unwrap(),
            )
        })
        .collect();
    serialize(views, metadata).unwrap()
}

/// Metadata of a model file; `mlp` = (mlp_power, inputs) when the file holds an MLP.
fn metadata(chart: &str, mlp: Option<(u32, MlpInputs)>) -> HashMap<String, String> {
    let mut m = HashMap::new();
    m.insert("format".to_string(), FORMAT.to_string());
    m.insert("chart".to_string(), chart.to_string());
    if let Some((k, inputs)) = mlp {
        m.insert("mlp_power".to_string(), k.to_string());
        m.insert("mlp_inputs".to_string(), inputs.name().to_string());
    }
    m.insert("system".to_string(), "rigid_body".to_string());
    m.insert("inertia".to_string(), "[1.5, 2.0, 2.5]".to_string());
    m
}

fn polynomial_tensors(poly: &Polynomial<3>) -> Vec<Tensor> {
    let n = poly.terms().len();
    let powers: Vec<i64> = poly
        .terms()
        .iter()
        .flat_map(|m| {
            [
                m.t_power as i64,
                m.p_powers[0] as i64,
                m.p_powers[1] as i64,
                m.p_powers[2] as i64,
            ]
        })
        .collect();
    let coeffs: Vec<f64> = poly.terms().iter().map(|m| m.coeff).collect();
    vec![
        i64_tensor("poly.powers", &[n, 4], &powers),
        f64_tensor("poly.coeffs", &[n], &coeffs),
    ]
}

fn mlp_tensors(mlp: &Mlp) -> Vec<Tensor> {
    mlp.layers
        .iter()
        .enumerate()
        .flat_map(|(i, l)| {
            [
                f64_tensor(&format!("mlp.{i}.weight"), &[l.n_out, l.n_in], &l.weight),
                f64_tensor(&format!("mlp.{i}.bias"), &[l.n_out], &l.bias),
            ]
        })
        .collect()
}

fn generating_tensors(gf: &GeneratingFunction<3>) -> Vec<Tensor> {
    let mut t = polynomial_tensors(&gf.polynomial);
    if let Some(mlp) = &gf.mlp {
        t.extend(mlp_tensors(mlp));
    }
    t
}

/// A valid model: −tH + small terms + t^m MLP.
fn valid_model(seed: u64) -> (GeneratingFunction<3>, Vec<Tensor>, HashMap<String, String>) {
    let mut rng = Rng::new(seed);
    let gf = random_generating(&mut rng, MlpInputs::Plain);
    let tensors = generating_tensors(&gf);
    let meta = metadata("cayley", Some((gf.mlp_power, gf.inputs)));
    (gf, tensors, meta)
}

fn valid_bytes() -> Vec<u8> {
    let (_, tensors, meta) = valid_model(0x5EED_0040);
    serialize_tensors(&tensors, Some(meta))
}

/// `Model::from_bytes` must give `CoreError::Format` with a message containing `needle`, and must
/// not panic.
#[track_caller]
fn expect_format_error(bytes: &[u8], needle: &str, what: &str) {
    match catch_unwind(AssertUnwindSafe(|| Model::from_bytes(bytes))) {
        Ok(Err(CoreError::Format(m))) => assert!(
            m.contains(needle),
            "{what}: message {m:?} does not mention {needle:?}"
        ),
        Ok(other) => panic!("{what}: expected CoreError::Format, got {other:?}"),
        Err(_) => panic!("{what}: Model::from_bytes panicked"),
    }
}

#[test]
fn model_round_trips_through_safetensors() {
    for (seed, chart_name, chart, inputs) in [
        (0x5EED_0041, "cayley", Chart::Cayley, MlpInputs::Plain),
        (0x5EED_0042, "exp", Chart::Exp, MlpInputs::Homogeneous),
        (0x5EED_0043, "cayley", Chart::Cayley, MlpInputs::Homogeneous),
    ] {
        let mut rng = Rng::new(seed);
        let gf = random_generating(&mut rng, inputs);
        let bytes = serialize_tensors(
            &generating_tensors(&gf),
            Some(metadata(chart_name, Some((gf.mlp_power, inputs)))),
        );
        let model = Model::from_bytes(&bytes).unwrap();
        assert_eq!(model.chart, chart);
        assert_eq!(model.generating::<3>().unwrap().inputs, inputs);
        assert_eq!(model.generating::<3>().unwrap(), gf);
        assert_eq!(model.metadata["system"], "rigid_body");
        assert_eq!(model.metadata["inertia"], "[1.5, 2.0, 2.5]");
        // It evaluates bit-for-bit like the directly built one.
        let (mut w1, mut w2) = (gf.workspace(), model.generating::<3>().unwrap().workspace());
        for _ in 0..20 {
            let t = rng.range(0.0, 1.0);
            let p = rng.vec3(-3.0, 3.0);
            let (a, b) = (
                gf.jet(t, &p, &mut w1),
                model.generating::<3>().unwrap().jet(t, &p, &mut w2),
            );
            assert!(a
                .flat()
                .iter()
                .zip(&b.flat())
                .all(|(x, y)| x.to_bits() == y.to_bits()));
            let (a, b) = (
                gf.value_and_time_derivative(t, &p, &mut w1),
                model
                    .generating::<3>()
                    .unwrap()
                    .value_and_time_derivative(t, &p, &mut w2),
            );
            assert_eq!(a.0.to_bits(), b.0.to_bits());
            assert_eq!(a.1.to_bits(), b.1.to_bits());
        }
        // Its stepper steps like the directly built one.
        let st = model.stepper::<3>(NewtonOptions::default()).unwrap();
        let direct = stepper(gf, chart);
        let mu0 = [1.0, 1.0, 2.0];
        let (mut a, mut b) = (mu0, mu0);
        st.step(0.1, &mut a, &mut w1).unwrap();
        direct.step(0.1, &mut b, &mut w2).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, mu0);
    }
    // Polynomial only (no MLP, no mlp_power needed) and MLP only (no polynomial tensors).
    let poly = Polynomial::new(taylor3()).unwrap();
    let bytes = serialize_tensors(&polynomial_tensors(&poly), Some(metadata("cayley", None)));
    let model = Model::from_bytes(&bytes).unwrap();
    assert_eq!(model.generating::<3>().unwrap().polynomial, poly);
    assert!(model.generating::<3>().unwrap().mlp.is_none());
    let mut rng = Rng::new(0x5EED_0044);
    let mlp = random_mlp(&mut rng, 8, 1.0);
    let bytes = serialize_tensors(
        &mlp_tensors(&mlp),
        Some(metadata("exp", Some((3, MlpInputs::Plain)))),
    );
    let model = Model::from_bytes(&bytes).unwrap();
    assert_eq!(model.generating::<3>().unwrap().mlp.as_ref(), Some(&mlp));
    assert_eq!(model.generating::<3>().unwrap().mlp_power, 3);
    assert!(model
        .generating::<3>()
        .unwrap()
        .polynomial
        .terms()
        .is_empty());
}

#[test]
fn model_from_file_round_trip_and_missing_path() {
    let bytes = valid_bytes();
    let dir = std::env::temp_dir();
    let path = dir.join(format!(
        "poisson_rs_test_{}.safetensors",
        std::process::id()
    ));
    std::fs::write(&path, &bytes).unwrap();
    let loaded = Model::from_file(&path);
    std::fs::remove_file(&path).unwrap();
    let from_bytes = Model::from_bytes(&bytes).unwrap();
    assert_eq!(
        loaded.unwrap().generating::<3>().unwrap(),
        from_bytes.generating::<3>().unwrap()
    );

    let missing = dir.join("poisson_rs_test_this_file_does_not_exist.safetensors");
    match Model::from_file(&missing) {
        Err(CoreError::NotFound(m)) => assert!(m.contains("does_not_exist"), "{m}"),
        other => panic!("expected NotFound, got {other:?}"),
    }
    // A directory is an I/O error, not a format error and not a panic.
    match Model::from_file(&dir) {
        Err(CoreError::Io(_)) => {}
        other => panic!("expected Io for a directory, got {other:?}"),
    }
}

#[test]
fn model_rejects_empty_and_truncated_bytes() {
    expect_format_error(&[], "not a readable safetensors file", "empty bytes");
    let bytes = valid_bytes();
    assert!(Model::from_bytes(&bytes).is_ok());
    for len in 0..bytes.len() {
        expect_format_error(
            &bytes[..len],
            "not a readable safetensors file",
            &format!("prefix of {len} of {} bytes", bytes.len()),
        );
    }
    // Trailing garbage is refused too.
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0; 8]);
    expect_format_error(
        &longer,
        "not a readable safetensors file",
        "8 trailing bytes",
    );
}

/// Random byte changes in the header (and its length prefix) never panic: the result is either a
/// model or a format error.
#[test]
fn model_survives_random_header_corruption() {
    let bytes = valid_bytes();
    let header_len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut rng = Rng::new(0x5EED_0050);
    let (mut n_ok, mut n_err) = (0, 0);
    for trial in 0..3000 {
        let mut b = bytes.clone();
        let n_flips = 1 + rng.below(3);
        for _ in 0..n_flips {
            let at = rng.below(8 + header_len);
            if rng.below(2) == 0 {
                b[at] ^= 1 << rng.below(8);
            } else {
                b[at] = rng.below(256) as u8;
            }
        }
        match catch_unwind(AssertUnwindSafe(|| Model::from_bytes(&b))) {
            Ok(Ok(_)) => n_ok += 1,
            Ok(Err(CoreError::Format(m))) => {
                assert!(!m.is_empty());
                n_err += 1
            }
            Ok(Err(e)) => panic!("trial {trial}: expected Format, got {e:?}"),
            Err(_) => panic!("trial {trial}: Model::from_bytes panicked"),
        }
    }
    // Most corruptions are caught; a few (a digit of a metadata value) still load.
    eprintln!("header corruption: {n_ok} loaded, {n_err} refused");
    assert!(n_err > 2000, "{n_ok} loaded, {n_err} refused");
}

#[test]
fn model_rejects_bad_metadata() {
    let (gf, tensors, meta) = valid_model(0x5EED_0060);
    let with = |edit: &dyn Fn(&mut HashMap<String, String>)| {
        let mut m = meta.clone();
        edit(&mut m);
        serialize_tensors(&tensors, Some(m))
    };
    expect_format_error(
        &serialize_tensors(&tensors, None),
        "no metadata",
        "no metadata",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("format");
        }),
        "'format' is missing",
        "missing format",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("format".into(), "poisson_rs.generating/2".into());
        }),
        "poisson_rs.generating/2",
        "wrong format",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("format".into(), "".into());
        }),
        "format",
        "empty format",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("chart");
        }),
        "'chart' is missing",
        "missing chart",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("chart".into(), "quaternion".into());
        }),
        "unknown chart 'quaternion'",
        "unknown chart",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("chart".into(), "Cayley".into());
        }),
        "unknown chart",
        "chart names are case-sensitive",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("mlp_power");
        }),
        "'mlp_power' is missing",
        "missing mlp_power",
    );
    expect_format_error(
        &with(&|m| {
            m.remove("mlp_inputs");
        }),
        "'mlp_inputs' is missing",
        "missing mlp_inputs",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("mlp_inputs".into(), "polar".into());
        }),
        "unknown mlp_inputs 'polar'",
        "unknown mlp_inputs",
    );
    expect_format_error(
        &with(&|m| {
            m.insert("mlp_power".into(), "0".into());
        }),
        "mlp_power must be at least 1",
        "mlp_power 0",
    );
    for bad in ["-1", "three", "2.5", ""] {
        expect_format_error(
            &with(&|m| {
                m.insert("mlp_power".into(), bad.into());
            }),
            "mlp_power",
            &format!("mlp_power {bad:?}"),
        );
    }
    assert!(
        Model::from_bytes(&with(&|_| {}))
            .unwrap()
            .generating::<3>()
            .unwrap()
            == gf
    );
}

#[test]
fn model_rejects_bad_polynomials() {
    let meta = metadata("cayley", None);
    let poly = |powers: &[i64], coeffs: &[f64]| {
        serialize_tensors(
            &[
                i64_tensor("poly.powers", &[coeffs.len(), 4], powers),
                f64_tensor("poly.coeffs", &[coeffs.len()], coeffs),
            ],
            Some(meta.clone()),
        )
    };
    // Valid to start with.
    assert!(Model::from_bytes(&poly(&[1, 2, 0, 0, 3, 0, 2, 2], &[-0.5, 0.1])).is_ok());
    expect_format_error(
        &poly(&[1, 2, 0, 0, 0, 0, 2, 2], &[-0.5, 0.1]),
        "t-power 0",
        "a t-power-0 term",
    );
    expect_format_error(
        &poly(&[1, 2, 0, 0, 3, 0, 2, 2], &[-0.5, f64::NAN]),
        "not finite",
        "a NaN coefficient",
    );
    expect_format_error(
        &poly(&[1, -2, 0, 0], &[1.0]),
        "exponent -2",
        "a negative exponent",
    );
    expect_format_error(
        &poly(&[1, 2, 0, 1000], &[1.0]),
        "exponent 1000",
        "a huge exponent",
    );
    // Shapes and dtypes.
    expect_format_error(
        &serialize_tensors(
            &[
                i64_tensor("poly.powers", &[2, 3], &[1, 2, 0, 1, 0, 2]),
                f64_tensor("poly.coeffs", &[2], &[1.0, 1.0]),
            ],
            Some(meta.clone()),
        ),
        "needs the tensor algebra.structure_constants",
        "powers of shape (2, 3)",
    );
    expect_format_error(
        &serialize_tensors(
            &[
                i64_tensor("poly.powers", &[1, 4], &[1, 2, 0, 0]),
                f64_tensor("poly.coeffs", &[2], &[1.0, 1.0]),
            ],
            Some(meta.clone()),
        ),
        "poly.coeffs has shape",
        "coeffs longer than powers",
    );
    expect_format_error(
        &serialize_tensors(
            &[
                f64_tensor("poly.powers", &[1, 4], &[1.0, 2.0, 0.0, 0.0]),
                f64_tensor("poly.coeffs", &[1], &[1.0]),
            ],
            Some(meta.clone()),
        ),
        "must be int64",
        "float powers",
    );
    expect_format_error(
        &serialize_tensors(
            &[i64_tensor("poly.powers", &[1, 4], &[1, 2, 0, 0])],
            Some(meta.clone()),
        ),
        "poly.coeffs",
        "coeffs missing",
    );
    expect_format_error(
        &serialize_tensors(
            &[f64_tensor("poly.coeffs", &[1], &[1.0])],
            Some(meta.clone()),
        ),
        "poly.powers",
        "powers missing",
    );
}

#[test]
fn model_rejects_bad_mlps() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    let layer = |i: usize, n_out: usize, n_in: usize, v: f64| {
        [
            f64_tensor(
                &format!("mlp.{i}.weight"),
                &[n_out, n_in],
                &vec![v; n_out * n_in],
            ),
            f64_tensor(&format!("mlp.{i}.bias"), &[n_out], &vec![0.1; n_out]),
        ]
    };
    let file = |layers: Vec<[Tensor; 2]>| {
        let t: Vec<Tensor> = layers.into_iter().flatten().collect();
        serialize_tensors(&t, Some(meta.clone()))
    };
    // Valid to start with.
    assert!(Model::from_bytes(&file(vec![layer(0, 8, 4, 0.1), layer(1, 1, 8, 0.1)])).is_ok());

    // A NaN (or infinite) weight.
    let mut l0 = layer(0, 8, 4, 0.1);
    let mut w = vec![0.1; 32];
    w[17] = f64::NAN;
    l0[0] = f64_tensor("mlp.0.weight", &[8, 4], &w);
    expect_format_error(
        &file(vec![l0.clone(), layer(1, 1, 8, 0.1)]),
        "NaN",
        "a NaN weight",
    );
    w[17] = f64::NEG_INFINITY;
    l0[0] = f64_tensor("mlp.0.weight", &[8, 4], &w);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "infinite",
        "an infinite weight",
    );
    let mut l1 = layer(1, 1, 8, 0.1);
    l1[1] = f64_tensor("mlp.1.bias", &[1], &[f64::NAN]);
    expect_format_error(&file(vec![layer(0, 8, 4, 0.1), l1]), "NaN", "a NaN bias");

    // An F32 weight tensor.
    let mut l0 = layer(0, 8, 4, 0.1);
    l0[0] = f32_tensor("mlp.0.weight", &[8, 4], &[0.1; 32]);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "must be float64",
        "an F32 weight",
    );

    // Mismatched layer shapes.
    expect_format_error(
        &file(vec![layer(0, 8, 4, 0.1), layer(1, 1, 5, 0.1)]),
        "layer 0 has 8 outputs but layer 1 takes 5 inputs",
        "mismatched layers",
    );
    let mut l0 = layer(0, 8, 4, 0.1);
    l0[1] = f64_tensor("mlp.0.bias", &[7], &[0.0; 7]);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "do not match",
        "bias of the wrong length",
    );
    let mut l0 = layer(0, 8, 4, 0.1);
    l0[0] = f64_tensor("mlp.0.weight", &[32], &[0.1; 32]);
    expect_format_error(
        &file(vec![l0, layer(1, 1, 8, 0.1)]),
        "do not match",
        "a 1-d weight",
    );

    // First layer not taking 4 inputs; last layer not 1 output.
    expect_format_error(
        &file(vec![layer(0, 8, 3, 0.1), layer(1, 1, 8, 0.1)]),
        "needs the tensor algebra.structure_constants",
        "first layer with 3 inputs",
    );
    expect_format_error(
        &file(vec![layer(0, 8, 4, 0.1), layer(1, 2, 8, 0.1)]),
        "must have 1 output",
        "last layer with 2 outputs",
    );
    // A missing layer in the middle, a missing bias.
    expect_format_error(
        &file(vec![layer(0, 8, 4, 0.1), layer(2, 1, 8, 0.1)]),
        "mlp.1.weight",
        "layer 1 missing",
    );
    let l0 = layer(0, 1, 4, 0.1);
    expect_format_error(
        &serialize_tensors(&[l0[0].clone()], Some(meta.clone())),
        "mlp.0.bias",
        "bias missing",
    );

    // An unexpected tensor, and no tensors at all.
    let mut t: Vec<Tensor> = [layer(0, 8, 4, 0.1), layer(1, 1, 8, 0.1)]
        .into_iter()
        .flatten()
        .collect();
    t.push(f64_tensor("optimizer.state", &[2], &[0.0, 1.0]));
    expect_format_error(
        &serialize_tensors(&t, Some(meta.clone())),
        "unexpected tensor 'optimizer.state'",
        "an unexpected tensor",
    );
    let mut t: Vec<Tensor> = layer(0, 1, 4, 0.1).to_vec();
    t.push(f64_tensor("mlp.0.scale", &[1], &[1.0]));
    expect_format_error(
        &serialize_tensors(&t, Some(meta.clone())),
        "unexpected tensor 'mlp.0.scale'",
        "mlp.0.scale",
    );
    expect_format_error(
        &serialize_tensors(&[], Some(meta.clone())),
        "neither polynomial terms nor an MLP",
        "no tensors",
    );
}

/// A tensor whose layer index is usize::MAX must be a format error, not an arithmetic overflow
/// (`n_layers.max(i + 1)` in model.rs panics in debug builds and wraps to 0 in release builds,
/// where the tensor is then silently ignored).
#[test]
fn model_rejects_absurd_layer_index() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    let mut t = polynomial_tensors(&Polynomial::new(minus_t_h()).unwrap());
    t.push(f64_tensor(
        &format!("mlp.{}.weight", usize::MAX),
        &[1],
        &[1.0],
    ));
    expect_format_error(
        &serialize_tensors(&t, Some(meta.clone())),
        "mlp",
        "layer index usize::MAX",
    );
}

/// Layer names must be spelled canonically: `mlp.+0.weight` or `mlp.00.bias` beside a valid
/// `mlp.0.weight` are extra tensors the loader would otherwise ignore (`usize::from_str` accepts
/// a leading `+` and leading zeros).
#[test]
fn model_rejects_non_canonical_layer_names() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    for alias in ["mlp.+0.weight", "mlp.00.bias"] {
        let mut rng = Rng::new(0x5EED_0070);
        let mlp = random_mlp(&mut rng, 4, 1.0);
        let mut t = mlp_tensors(&mlp);
        t.push(f64_tensor(alias, &[1], &[1.0]));
        expect_format_error(&serialize_tensors(&t, Some(meta.clone())), alias, alias);
    }
}

/// mlp_power above i32::MAX is cast to a negative exponent in `t.powi(m as i32)`: it must be
/// refused or evaluate correctly (t^m → 0 for t < 1), never silently produce inf.
#[test]
fn model_huge_mlp_power_is_refused_or_correct() {
    let mut rng = Rng::new(0x5EED_0071);
    let mlp = random_mlp(&mut rng, 4, 1.0);
    let mut t = polynomial_tensors(&Polynomial::new(minus_t_h()).unwrap());
    t.extend(mlp_tensors(&mlp));
    let bytes = serialize_tensors(
        &t,
        Some(metadata("cayley", Some((3_000_000_000, MlpInputs::Plain)))),
    );
    match Model::from_bytes(&bytes) {
        Err(CoreError::Format(m)) => assert!(m.contains("mlp_power"), "{m}"),
        Ok(model) => {
            let mut ws = model.generating::<3>().unwrap().workspace();
            let p = [1.0, 1.0, 2.0];
            let jet = model.generating::<3>().unwrap().jet(0.5, &p, &mut ws);
            let (v, dt) = model
                .generating::<3>()
                .unwrap()
                .value_and_time_derivative(0.5, &p, &mut ws);
            assert!(
                jet.is_finite() && v.is_finite() && dt.is_finite(),
                "jet {jet:?} v {v} dt {dt}"
            );
        }
        Err(e) => panic!("expected Format, got {e:?}"),
    }
}

// ---------------------------------------------------------------------------------------------
// 5. The exponential chart against an independent implementation
// ---------------------------------------------------------------------------------------------

/// A layer index of 4e9 would make the loader reserve ~256 GB before reading any layer, and the
/// allocation failure would abort the whole process: the index must be refused first.
#[test]
fn model_rejects_huge_layer_index() {
    let meta = metadata("cayley", Some((3, MlpInputs::Plain)));
    let mut t = polynomial_tensors(&Polynomial::new(minus_t_h()).unwrap());
    t.push(f64_tensor("mlp.4000000000.weight", &[1], &[1.0]));
    expect_format_error(&serialize_tensors(&t, Some(meta)), "mlp", "layer index 4e9");
}

// ---------------------------------------------------------------------------------------------
// 6. Segmented rollouts and a property-based fuzz of the model loader
// ---------------------------------------------------------------------------------------------

/// `Model::from_bytes` on arbitrary input either loads or returns `CoreError::Format`; it never
/// panics (proptest turns a panic into a failing, shrunk case). Seeded, so it reproduces.
mod loader_fuzz {
    use proptest::prelude::*;
    use proptest::sample::Index;
    use proptest::test_runner::{Config, RngSeed};

    use super::{f64_tensor, i64_tensor, metadata, serialize_tensors, valid_bytes, Tensor};
    use crate::error::CoreError;
    use crate::generating::MlpInputs;
    use crate::model::Model;

    fn config() -> Config {
        Config {
            cases: 2000,
            failure_persistence: None,
            rng_seed: RngSeed::Fixed(0x5EED_0080),
            ..Config::default()
        }
    }

    /// Ok or a non-empty Format error; anything else (another variant, a panic) fails the case.
    fn check(bytes: &[u8]) -> Result<(), TestCaseError> {
        match Model::from_bytes(bytes) {
            Ok(_) => Ok(()),
            Err(CoreError::Format(m)) if !m.is_empty() => Ok(()),
            Err(e) => Err(TestCaseError::fail(format!("unexpected error {e:?}"))),
        }
    }

    /// One edit of a byte string: overwrite, bit flip, insertion, deletion or truncation.
    #[derive(Clone, Debug)]
    enum Edit {
        Set(Index, u8),
        Flip(Index, u8),
        Insert(Index, Vec<u8>),
        Delete(Index, usize),
        Truncate(Index),
    }

    fn edit() -> impl Strategy<Value = Edit> {
        prop_oneof![
            (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Set(i, b)),
            (any::<Index>(), 0u8..8).prop_map(|(i, b)| Edit::Flip(i, b)),
            (any::<Index>(), prop::collection::vec(any::<u8>(), 1..16))
                .prop_map(|(i, v)| Edit::Insert(i, v)),
            (any::<Index>(), 1usize..64).prop_map(|(i, n)| Edit::Delete(i, n)),
            any::<Index>().prop_map(Edit::Truncate),
        ]
    }

    fn apply(bytes: &mut Vec<u8>, e: &Edit) {
        if bytes.is_empty() {
            return;
        }
        match e {
            Edit::Set(i, b) => {
                let at = i.index(bytes.len());
                bytes[at] = *b;
            }
            Edit::Flip(i, bit) => {
                let at = i.index(bytes.len());
                bytes[at] ^= 1 << bit;
            }
            Edit::Insert(i, v) => {
                let at = i.index(bytes.len() + 1);
                bytes.splice(at..at, v.iter().copied());
            }
            Edit::Delete(i, n) => {
                let at = i.index(bytes.len());
                let end = (at + n).min(bytes.len());
                bytes.drain(at..end);
            }
            Edit::Truncate(i) => {
                let at = i.index(bytes.len());
                bytes.truncate(at);
            }
        }
    }

    proptest! {
        #![proptest_config(config())]

        #[test]
        fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            check(&bytes)?;
        }

        /// Random bytes behind a plausible header length, so the parser gets past the prefix.
        #[test]
        fn random_headers_never_panic(body in prop::collection::vec(any::<u8>(), 0..600),
                                      len in 0u64..700) {
            let mut bytes = len.to_le_bytes().to_vec();
            bytes.extend(body);
            check(&bytes)?;
        }

        /// Well-formed safetensors with random declared shapes for every tensor a model file
        /// can hold: structure constants (any rank and sizes, dimensions 0..12), polynomial
        /// rows of any width, and MLP layers of any widths (zero included) and count. Whatever
        /// the shapes, loading returns a model or a format error.
        #[test]
        fn random_tensor_shapes_never_panic(
            algebra in prop::option::of(prop::collection::vec(0usize..12, 0..5)),
            poly in prop::option::of((0usize..6, 0usize..13, 0i64..70)),
            layers in prop::collection::vec((0usize..9, 0usize..9), 0..4),
            mlp_power in 0u32..70,
            chart in prop::sample::select(vec!["exp", "cayley"]),
        ) {
            let mut tensors: Vec<Tensor> = Vec::new();
            if let Some(shape) = &algebra {
                let n: usize = shape.iter().product();
                // Antisymmetric-looking numbers are not needed: shape checks come first.
                tensors.push(f64_tensor("algebra.structure_constants", shape, &vec![0.5; n]));
            }
            if let Some((rows, width, power)) = poly {
                tensors.push(i64_tensor("poly.powers", &[rows, width], &vec![power; rows * width]));
                tensors.push(f64_tensor("poly.coeffs", &[rows], &vec![1.0; rows]));
            }
            for (i, &(n_out, n_in)) in layers.iter().enumerate() {
                tensors.push(f64_tensor(&format!("mlp.{i}.weight"), &[n_out, n_in],
                                        &vec![0.1; n_out * n_in]));
                tensors.push(f64_tensor(&format!("mlp.{i}.bias"), &[n_out], &vec![0.0; n_out]));
            }
            let meta = metadata(chart, (!layers.is_empty()).then_some((mlp_power, MlpInputs::Plain)));
            check(&serialize_tensors(&tensors, Some(meta)))?;
        }

        /// 1–8 random edits anywhere in a valid file (header, metadata, tensor data).
        #[test]
        fn mutated_valid_files_never_panic(edits in prop::collection::vec(edit(), 1..8)) {
            let mut bytes = valid_bytes();
            for e in &edits {
                apply(&mut bytes, e);
            }
            check(&bytes)?;
        }
    }
}

// ---------------------------------------------------------------------------------------------
