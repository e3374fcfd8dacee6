//! Rollout throughput (steps per second) and the cost of one Newton step.
//!
//! Uses the shipped default model when `python/poisson_rs/models/default.safetensors` exists,
//! else a seeded random stand-in of the same kind: the Taylor K=3 polynomial for
//! I = (1.5, 2, 2.5) (Cayley chart) plus t⁵ · MLP with hidden widths (32, 32).
//!
//! Also: Taylor-HJ bisection steps in lockstep SIMD lanes against one trajectory at a time
//! (`bisection_lanes`), the batched layer kernel alone on a 250×250 layer, and rollouts of the 500-250-250-250
//! `paper` model (or a random stand-in of its size) in steps/s and, under full Newton, flops/s.
//!
//! And RK4 on three point vortices with the field as a Hamiltonian's program (interpreted)
//! against the same field written out by hand (`classical/vortices`); the rigid body's Taylor
//! K = 3 step in the exponential chart by the package's solver against the same step map
//! written out by hand, and RK4 (`taylor3-exp`); the heavy top's Taylor K = 3 step on se(3)
//! against its RK4 (`taylor3-heavy-top`).
//!
//! Each rollout size does a few thousand to twenty thousand steps per iteration, so
//! `cargo bench --bench rollout` takes about three minutes on two cores.

use std::hint::black_box;
use std::path::Path;
use std::sync::OnceLock;
use std::time::Duration;

use criterion::{
    criterion_group, criterion_main, BenchmarkId, Criterion, SamplingMode, Throughput,
};
use poisson_rs::structures::lie_groupoid::{COS_SERIES, C_SERIES, SIN_SERIES};
use poisson_rs::{
    kernel, m3, rollout, v3, BisectionStepper, Chart, GeneratingFunction, Groupoid, Layer, Mlp,
    MlpInputs, Model, Monomial, NewtonOptions, Polynomial, StepMap,
};

/// Step size of the paper's scene.
const H: f64 = 0.1;

/// `n` steps of `h` of `mu0` by the chunk kernel `k` (the first and last states recorded into
/// `out`: 2 · len(mu0) · N numbers).
fn run_kernel<const N: usize, K: poisson_rs::rollout::ChunkKernel<N>>(
    k: &K,
    mu0: &[[f64; N]],
    h: f64,
    n: usize,
    out: &mut [f64],
) {
    let mut r = poisson_rs::rollout::Rollout::start(mu0, h, n, n, out).unwrap();
    r.advance_kernel(k, n, out, false).unwrap();
    black_box(r.info());
}

/// splitmix64, for reproducible weights and initial states.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }

    /// A uniformly random point on the sphere of radius `r`.
    fn sphere(&mut self, r: f64) -> [f64; 3] {
        loop {
            let v = [
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            ];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n > 0.1 && n <= 1.0 {
                return v.map(|c| r * c / n);
            }
        }
    }
}

/// t S₁ + t³ S₃ for I = (1.5, 2, 2.5), Cayley chart (DESIGN.md §1).
fn taylor3() -> Polynomial<3> {
    let terms: [(u32, [u32; 3], f64); 9] = [
        (1, [2, 0, 0], -1.0 / 3.0),
        (1, [0, 2, 0], -1.0 / 4.0),
        (1, [0, 0, 2], -1.0 / 5.0),
        (3, [4, 0, 0], -2.0 / 81.0),
        (3, [2, 2, 0], -71.0 / 2160.0),
        (3, [2, 0, 2], -17.0 / 675.0),
        (3, [0, 4, 0], -1.0 / 96.0),
        (3, [0, 2, 2], -11.0 / 720.0),
        (3, [0, 0, 4], -2.0 / 375.0),
    ];
    Polynomial::new(
        terms
            .iter()
            .map(|&(t_power, p_powers, coeff)| Monomial {
                t_power,
                p_powers,
                coeff,
            })
            .collect(),
    )
    .unwrap()
}

/// Taylor K=3 + t⁵ · MLP 4 → 32 → 32 → 1 with Xavier-uniform weights (seed 42).
fn random_model() -> BisectionStepper<3> {
    let mut rng = Rng(42);
    let widths = [4, 32, 32, 1];
    let layers = widths
        .windows(2)
        .map(|w| {
            let (n_in, n_out) = (w[0], w[1]);
            let a = (6.0 / (n_in + n_out) as f64).sqrt();
            let weight = (0..n_in * n_out).map(|_| rng.range(-a, a)).collect();
            let bias = (0..n_out).map(|_| rng.range(-0.1, 0.1)).collect();
            Layer::new(n_in, n_out, weight, bias).unwrap()
        })
        .collect();
    let mlp = Mlp::new(layers).unwrap();
    let generating = GeneratingFunction::new(taylor3(), Some(mlp), 5, MlpInputs::Plain).unwrap();
    BisectionStepper::new(
        generating,
        Groupoid::so3(Chart::Cayley).unwrap(),
        NewtonOptions::default(),
    )
}

/// The shipped 500-250-250-250 `paper` model, or a seeded random stand-in of that size.
fn paper_stepper(newton: NewtonOptions) -> BisectionStepper<3> {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("python/poisson_rs/models/paper.safetensors");
    if path.exists() {
        return Model::from_file(&path)
            .expect("the paper model file does not load")
            .stepper::<3>(newton)
            .expect("the paper model is three-dimensional");
    }
    println!("paper model not found; using a seeded random 500-250-250-250 stand-in");
    let mut rng = Rng(43);
    let widths = [4, 500, 250, 250, 250, 1];
    let layers = widths
        .windows(2)
        .map(|w| {
            let (n_in, n_out) = (w[0], w[1]);
            let a = 0.1 * (6.0 / (n_in + n_out) as f64).sqrt();
            let weight = (0..n_in * n_out).map(|_| rng.range(-a, a)).collect();
            Layer::new(n_in, n_out, weight, vec![0.0; n_out]).unwrap()
        })
        .collect();
    let terms = Polynomial::new(taylor3().terms()[..3].to_vec()).unwrap(); // −tH
    let mlp = Mlp::new(layers).unwrap();
    let generating = GeneratingFunction::new(terms, Some(mlp), 1, MlpInputs::Plain).unwrap();
    BisectionStepper::new(generating, Groupoid::so3(Chart::Cayley).unwrap(), newton)
}

/// Paper-sized MLP (253,501 parameters): steps/s with the default simplified Newton, and the
/// kernel's flop rate under full Newton, where every update is a value/gradient/Hessian pass
/// (20 flops per weight) and the final pass a reverse-mode gradient (4 per weight).
fn bench_paper(c: &mut Criterion) {
    let simplified = paper_stepper(NewtonOptions::default());
    let full = paper_stepper(NewtonOptions {
        simplified: false,
        ..NewtonOptions::default()
    });
    let weights: usize = simplified
        .generating
        .mlp
        .as_ref()
        .map_or(0, |m| m.layers.iter().map(|l| l.weight.len()).sum());
    let mut group = c.benchmark_group("rollout_paper");
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.sampling_mode(SamplingMode::Flat);
    for (batch, n_steps) in [(1usize, 20usize), (64, 4), (4096, 1)] {
        let mu0 = initial_states(batch);
        let mut out = vec![0.0; batch * (n_steps + 1) * 3];
        let infos = rollout(&full, &mu0, H, n_steps, 1, &mut out).unwrap();
        assert!(
            infos.iter().all(|i| i.converged),
            "paper bench trajectories failed"
        );
        let updates: u64 = infos.iter().map(|i| i.newton_iterations).sum();
        let flops = (20 * updates + 4 * (batch * n_steps) as u64) * weights as u64;
        // Batch 4096 takes about a second per iteration.
        group.measurement_time(Duration::from_secs(if batch == 4096 { 15 } else { 4 }));
        for (name, stepper, throughput) in [
            (
                "steps",
                &simplified,
                Throughput::Elements((batch * n_steps) as u64),
            ),
            ("full_newton_flops", &full, Throughput::Elements(flops)),
        ] {
            group.throughput(throughput);
            group.bench_with_input(
                BenchmarkId::new(name, format!("batch={batch}")),
                &mu0,
                |b, mu0| {
                    b.iter(|| {
                        let infos = rollout(stepper, black_box(mu0), H, n_steps, 1, &mut out);
                        black_box(infos.unwrap())
                    })
                },
            );
        }
    }
    group.finish();
}

fn load_stepper() -> BisectionStepper<3> {
    static STEPPER: OnceLock<BisectionStepper<3>> = OnceLock::new();
    STEPPER.get_or_init(load_stepper_once).clone()
}

fn load_stepper_once() -> BisectionStepper<3> {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("python/poisson_rs/models/default.safetensors");
    if path.exists() {
        let model = Model::from_file(&path).expect("the default model file does not load");
        let n = model.mlp.as_ref().map_or(0, Mlp::n_parameters);
        println!(
            "bench model: {} (chart {}, {} MLP parameters, {} polynomial terms)",
            path.display(),
            model.chart.name(),
            n,
            model.n_polynomial_terms()
        );
        model
            .stepper::<3>(NewtonOptions::default())
            .expect("a rigid-body model")
    } else {
        println!(
            "bench model: {} not found; using a seeded random stand-in \
             (Taylor K=3 + t^5 MLP 4-32-32-1, Cayley)",
            path.display()
        );
        random_model()
    }
}

/// `n` initial states on spheres of radius 1 to 4.
fn initial_states(n: usize) -> Vec<[f64; 3]> {
    let mut rng = Rng(7);
    (0..n)
        .map(|_| {
            let r = rng.range(1.0, 4.0);
            rng.sphere(r)
        })
        .collect()
}

fn bench_rollout(c: &mut Criterion) {
    let stepper = load_stepper();
    let mut group = c.benchmark_group("rollout");
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(3));
    group.sampling_mode(SamplingMode::Flat);
    for (batch, n_steps) in [(1usize, 1000usize), (64, 50), (4096, 5)] {
        let mu0 = initial_states(batch);
        let mut out = vec![0.0; batch * (n_steps + 1) * 3];
        // Every trajectory must succeed, or the bench would time early exits.
        let infos = rollout(&stepper, &mu0, H, n_steps, 1, &mut out).unwrap();
        let failed = infos.iter().filter(|i| !i.converged).count();
        assert_eq!(failed, 0, "{failed} of {batch} bench trajectories failed");
        group.throughput(Throughput::Elements((batch * n_steps) as u64));
        group.bench_with_input(
            BenchmarkId::new(format!("steps={n_steps}"), format!("batch={batch}")),
            &mu0,
            |b, mu0| {
                b.iter(|| {
                    let infos = rollout(&stepper, black_box(mu0), H, n_steps, 1, &mut out);
                    black_box(infos.unwrap())
                })
            },
        );
    }
    group.finish();
}

fn bench_step(c: &mut Criterion) {
    let stepper = load_stepper();
    let mut ws = stepper.workspace();
    let mu0 = [1.0, 1.0, 2.0];
    let mut probe = mu0;
    let stats = stepper.step(H, &mut probe, &mut ws).unwrap();
    println!(
        "one step from {mu0:?}: {} Newton updates, residual {:e}",
        stats.iterations, stats.residual
    );
    let mut group = c.benchmark_group("newton_step");
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(2));
    group.throughput(Throughput::Elements(1));
    group.bench_function("step", |b| {
        b.iter(|| {
            let mut mu = black_box(mu0);
            let r = stepper.step(H, &mut mu, &mut ws);
            black_box((r, mu))
        })
    });
    // One evaluation of S, ∇S and ∇²S: a Newton update costs about one of these.
    let gf = &stepper.generating;
    let mut gws = gf.workspace();
    group.bench_function("jet", |b| {
        b.iter(|| black_box(gf.jet(black_box(H), black_box(&mu0), &mut gws)))
    });
    group.finish();
}

/// The batched layer kernel alone, on one thread: a 250×250 layer of the paper's network against
/// the jets (10 columns each) of 1 and of 16 trajectories. Throughput counts flops
/// (2 per weight and column), to set beside a BLAS GEMM on one core.
fn bench_kernel(c: &mut Criterion) {
    let mut rng = Rng(3);
    let (n_in, n_out) = (250, 250);
    let w: Vec<f64> = (0..n_in * n_out).map(|_| rng.range(-0.1, 0.1)).collect();
    let packed = kernel::pack(&w, n_in, n_out);
    println!("kernel: fused multiply-add {}", kernel::uses_fma());
    let mut group = c.benchmark_group("kernel_250x250");
    group.sample_size(20);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(2));
    for trajectories in [1usize, 16] {
        let cols = 10 * trajectories;
        let x: Vec<f64> = (0..n_in * cols).map(|_| rng.range(-1.0, 1.0)).collect();
        let mut z = vec![0.0; n_out * cols];
        group.throughput(Throughput::Elements((2 * n_in * n_out * cols) as u64));
        group.bench_function(
            BenchmarkId::new("flops", format!("trajectories={trajectories}")),
            |b| b.iter(|| kernel::gemm(&packed, n_in, n_out, black_box(&x), cols, &mut z)),
        );
    }
    group.finish();
}

/// RK4 and the implicit midpoint (masked Newton lanes) of the rigid body and the heavy top (its
/// straight-line se(3) kernel, and the generic compiled field), 4096 trajectories × 20 steps (final state kept): one trajectory at a time (the scalar
/// oracle), and in SIMD lanes on the portable and the widest dispatch path. `cargo bench --bench rollout -- classical`.
fn bench_classical(c: &mut Criterion) {
    use poisson_rs::classical::ImplicitMidpoint;
    use poisson_rs::lanes::{Isa, Lanes};
    use poisson_rs::rollout::PerStep;
    use poisson_rs::{LiePoisson, NewtonOptions, RigidBody, Rk4};

    fn group<const N: usize, F>(c: &mut Criterion, name: &str, field: F, mu0: Vec<[f64; N]>)
    where
        F: poisson_rs::VectorField<N> + poisson_rs::lanes::MidpointSolve<N> + Clone,
        Rk4<F>: poisson_rs::lanes::LaneStepper<N>,
        ImplicitMidpoint<F>: poisson_rs::lanes::LaneStepper<N>,
        nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
    {
        let n = 20;
        let mid = ImplicitMidpoint {
            system: field.clone(),
            newton: NewtonOptions::default(),
        };
        let rk4 = Rk4 { system: field };
        let mut out = vec![0.0; mu0.len() * 2 * N];
        let mut g = c.benchmark_group(format!("classical/{name}"));
        g.sample_size(10);
        g.warm_up_time(Duration::from_millis(500));
        g.measurement_time(Duration::from_secs(2));
        g.throughput(Throughput::Elements((mu0.len() * n) as u64));
        g.bench_function("scalar", |b| {
            b.iter(|| run_kernel(&PerStep(&rk4), &mu0, H, n, &mut out))
        });
        for isa in [Isa::PORTABLE, Isa::detect()] {
            let k = Lanes { stepper: &rk4, isa };
            g.bench_function(format!("lanes-{}", isa.name()), |b| {
                b.iter(|| run_kernel(&k, &mu0, H, n, &mut out))
            });
        }
        g.bench_function("midpoint-scalar", |b| {
            b.iter(|| run_kernel(&PerStep(&mid), &mu0, H, n, &mut out))
        });
        for isa in [Isa::PORTABLE, Isa::detect()] {
            let k = Lanes { stepper: &mid, isa };
            g.bench_function(format!("midpoint-lanes-{}", isa.name()), |b| {
                b.iter(|| run_kernel(&k, &mu0, H, n, &mut out))
            });
        }
        g.finish();
    }
    let mut rng = Rng(7);
    let rigid: Vec<[f64; 3]> = (0..4096)
        .map(|_| std::array::from_fn(|_| rng.range(-3.0, 3.0)))
        .collect();
    group(
        c,
        "rigid_body",
        RigidBody::new([1.5, 2.0, 2.5]).unwrap(),
        rigid,
    );
    let top = LiePoisson::heavy_top([1.0, 1.5, 2.0], [0.0, 0.0, 0.981]).unwrap();
    let states: Vec<[f64; 6]> = (0..4096)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    // The same system through the generic compiled field (run-time indices) and through the
    // straight-line se(3) kernel its data is recognised as (what `LieStepper` uses).
    group(c, "heavy_top_compiled", top.compile(), states.clone());
    let field = poisson_rs::straight_line::LieField::new(&top);
    assert_eq!(field.kernel_name(), "se3-quadratic-linear");
    group(c, "heavy_top", field, states);
}

/// The splittings, DMV and the heavy top's splitting, 4096 trajectories × 20 steps (final state
/// kept): one trajectory at a time (the scalar oracle, `PerStep`), and in SIMD lanes on the
/// portable and the widest dispatch path; for Strang also the scalar step as it was with libm's
/// sin/cos. `cargo bench --bench rollout -- classical/split`.
fn bench_splitting_lanes(c: &mut Criterion) {
    use poisson_rs::classical::{CasimirSplitting, HeavyTop, HeavyTopSplitting, MoserVeselov};
    use poisson_rs::lanes::{Isa, LaneStepper, Lanes};
    use poisson_rs::rollout::PerStep;
    use poisson_rs::stepper::StepResult;
    use poisson_rs::{NewtonOptions, RigidBody, Splitting, Splitting4};

    const STEPS: usize = 20;
    fn group<const N: usize, S>(c: &mut Criterion, name: &str, s: &S, mu0: &[[f64; N]])
    where
        S: LaneStepper<N> + StepMap<N, Workspace = ()>,
    {
        let mut out = vec![0.0; mu0.len() * 2 * N];
        let mut g = c.benchmark_group(format!("classical/split/{name}"));
        g.sample_size(10);
        g.warm_up_time(Duration::from_millis(500));
        g.measurement_time(Duration::from_secs(2));
        g.throughput(Throughput::Elements((mu0.len() * STEPS) as u64));
        g.bench_function("scalar", |b| {
            b.iter(|| run_kernel(&PerStep(s), mu0, H, STEPS, &mut out))
        });
        for isa in [Isa::PORTABLE, Isa::detect()] {
            let k = Lanes { stepper: s, isa };
            g.bench_function(format!("lanes-{}", isa.name()), |b| {
                b.iter(|| run_kernel(&k, mu0, H, STEPS, &mut out))
            });
        }
        g.finish();
    }

    /// The Strang step as it was before the branch-free sin/cos: the same rotations, libm's
    /// sin_cos one angle at a time.
    struct StrangLibm([f64; 3]);
    impl StepMap<3> for StrangLibm {
        type Workspace = ();
        fn workspace(&self) {}
        fn step(&self, h: f64, mu: &mut [f64; 3], _: &mut ()) -> StepResult {
            for (i, t) in [
                (0, 0.5 * h),
                (1, 0.5 * h),
                (2, h),
                (1, 0.5 * h),
                (0, 0.5 * h),
            ] {
                let (s, c) = (t * mu[i] * self.0[i]).sin_cos();
                let (a, b) = ((i + 1) % 3, (i + 2) % 3);
                let (x, y) = (mu[a], mu[b]);
                mu[a] = c * x + s * y;
                mu[b] = c * y - s * x;
            }
            if mu.iter().all(|v| v.is_finite()) {
                Ok(Default::default())
            } else {
                Err(poisson_rs::StepFailure::NonFinite)
            }
        }
    }

    let mut rng = Rng(11);
    let rigid: Vec<[f64; 3]> = (0..4096)
        .map(|_| std::array::from_fn(|_| rng.range(-3.0, 3.0)))
        .collect();
    let body = RigidBody::new([1.5, 2.0, 2.5]).unwrap();
    let strang = Splitting::strang(body);
    group(c, "splitting", &strang, &rigid);
    {
        let libm = StrangLibm(body.inverse_inertia());
        let mut out = vec![0.0; rigid.len() * 2 * 3];
        let mut g = c.benchmark_group("classical/split/splitting");
        g.sample_size(10);
        g.warm_up_time(Duration::from_millis(500));
        g.measurement_time(Duration::from_secs(2));
        g.throughput(Throughput::Elements((rigid.len() * STEPS) as u64));
        g.bench_function("scalar-libm", |b| {
            b.iter(|| run_kernel(&PerStep(&libm), &rigid, H, STEPS, &mut out))
        });
        g.finish();
    }
    group(c, "splitting4", &Splitting4::suzuki(body), &rigid);
    group(c, "splitting_casimir", &CasimirSplitting::new(body), &rigid);
    group(
        c,
        "dmv",
        &MoserVeselov::new(body, NewtonOptions::default()),
        &rigid,
    );
    let top = HeavyTopSplitting {
        top: HeavyTop::new([1.0, 1.5, 2.0], 0.981, [0.0, 0.0, 1.0]).unwrap(),
    };
    let states: Vec<[f64; 6]> = (0..4096)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    group::<6, _>(c, "heavy_top_splitting", &top, &states);
}

/// A stepper taken one trajectory at a time: the scalar path the lanes are measured against.
struct OneAtATime<'a>(&'a BisectionStepper<3>);

impl StepMap<3> for OneAtATime<'_> {
    type Workspace = <BisectionStepper<3> as StepMap<3>>::Workspace;
    fn workspace(&self) -> Self::Workspace {
        self.0.workspace()
    }
    fn step(
        &self,
        h: f64,
        mu: &mut [f64; 3],
        ws: &mut Self::Workspace,
    ) -> poisson_rs::stepper::StepResult {
        self.0.step(h, mu, ws)
    }
}

/// Taylor K=3 (Cayley chart) bisection steps of 4096 states: Newton in lockstep blocks with the
/// polynomial jets in SIMD lanes (the stepper's own batch) against one trajectory at a time (the
/// same bits). `cargo bench --bench rollout -- bisection_lanes`.
fn bench_bisection_lanes(c: &mut Criterion) {
    let stepper = BisectionStepper::new(
        GeneratingFunction::new(taylor3(), None, 0, MlpInputs::Plain).unwrap(),
        Groupoid::so3(Chart::Cayley).unwrap(),
        NewtonOptions::default(),
    );
    let (batch, n_steps) = (4096usize, 5usize);
    let mu0 = initial_states(batch);
    let mut out = vec![0.0; batch * (n_steps + 1) * 3];
    let mut group = c.benchmark_group("bisection_lanes");
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(3));
    group.sampling_mode(SamplingMode::Flat);
    group.throughput(Throughput::Elements((batch * n_steps) as u64));
    group.bench_function("taylor3-cayley/lockstep-lanes", |b| {
        b.iter(|| black_box(rollout(&stepper, black_box(&mu0), H, n_steps, 1, &mut out).unwrap()))
    });
    let scalar = OneAtATime(&stepper);
    group.bench_function("taylor3-cayley/one-at-a-time", |b| {
        b.iter(|| black_box(rollout(&scalar, black_box(&mu0), H, n_steps, 1, &mut out).unwrap()))
    });
    group.finish();
}

// The three point vortices' field program, Γ = (1, 1, 0.5) (scenes/point_vortices.toml), as
// `ExpressionSystem.field_program` writes it: the table the bindings receive.
#[rustfmt::skip]
const VORTEX_CODE: [i64; 76] = [1, 0, 1, 0, 3, 7, 1, 4, 1, 4, 0, 0, 3, 7, 4, 4, 2, 5, 4, 4, 4, 4, 1, 0, 3, 7, 4, 4, 0, 3, 7, 4, 4, 2, 5, 4, 4, 4, 4, 4, 4, 4, 4, 2, 2, 3, 7, 4, 4, 3, 7, 4, 4, 2, 5, 4, 4, 4, 4, 4, 4, 4, 4, 2, 2, 2, 2, 4, 4, 1, 4, 4, 1, 4, 1, 4];
#[rustfmt::skip]
const VORTEX_A: [i64; 76] = [0, 0, 0, 2, 1, 4, 0, 6, 0, 8, 1, 3, 10, 12, 6, 8, 5, 2, 17, 17, 17, 17, 0, 4, 1, 24, 6, 8, 5, 10, 29, 6, 8, 25, 2, 34, 34, 34, 34, 22, 22, 22, 22, 18, 19, 3, 45, 6, 8, 11, 49, 6, 8, 46, 2, 54, 54, 54, 54, 22, 22, 22, 22, 20, 21, 41, 42, 0, 0, 0, 69, 69, 0, 72, 0, 74];
#[rustfmt::skip]
const VORTEX_B: [i64; 76] = [0, 0, 0, 0, 3, 2, 0, 4, 0, 4, 0, 0, 11, 2, 12, 12, 13, 16, 7, 14, 9, 15, 0, 0, 23, 2, 24, 24, 0, 28, 2, 29, 29, 30, 33, 26, 31, 27, 32, 35, 36, 37, 38, 39, 40, 23, 2, 45, 45, 28, 2, 49, 49, 50, 53, 47, 51, 48, 52, 55, 56, 57, 58, 59, 60, 61, 62, 44, 64, 0, 43, 63, 0, 66, 0, 65];
#[rustfmt::skip]
const VORTEX_C: [f64; 76] = [-0.07957747154594767, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0, 0.0, -2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.07957747154594767, 0.0, 0.0, -0.15915494309189535, 0.0, 0.15915494309189535, 0.0];
#[rustfmt::skip]
const VORTEX_OUT: [i64; 6] = [67, 70, 68, 71, 73, 75];

/// RK4 on the three point vortices, 4096 trajectories × 20 steps: the field as the package runs
/// it (its program interpreted, [`poisson_rs::expression::Expression::values_lanes`]) against
/// the same field written out by hand in straight-line code (the Biot–Savart sums), both in
/// SIMD lanes through the same RK4. What an interpreter costs over compiled code:
/// `cargo bench --bench rollout -- classical/vortices`.
fn bench_expression_field(c: &mut Criterion) {
    use poisson_rs::expression::Expression;
    use poisson_rs::lane_field::LaneField;
    use poisson_rs::lanes::{Isa, Lanes};
    use poisson_rs::Rk4;

    struct Program(Expression);
    impl LaneField<6> for Program {
        const WIDE: bool = true;
        #[inline(always)]
        fn field_lanes<const L: usize>(&self, x: &[[f64; L]; 6], out: &mut [[f64; L]; 6]) {
            self.0.values_lanes(x, out);
        }
    }
    struct ByHand;
    impl LaneField<6> for ByHand {
        const WIDE: bool = true;
        #[inline(always)]
        fn field_lanes<const L: usize>(&self, x: &[[f64; L]; 6], out: &mut [[f64; L]; 6]) {
            const GAMMA: [f64; 3] = [1.0, 1.0, 0.5];
            for l in 0..L {
                let mut o = [0.0; 6];
                for i in 0..3 {
                    for j in i + 1..3 {
                        let (dx, dy) =
                            (x[2 * i][l] - x[2 * j][l], x[2 * i + 1][l] - x[2 * j + 1][l]);
                        let k = std::f64::consts::FRAC_1_PI / 2.0 / (dx * dx + dy * dy);
                        o[2 * i] -= GAMMA[j] * k * dy;
                        o[2 * i + 1] += GAMMA[j] * k * dx;
                        o[2 * j] += GAMMA[i] * k * dy;
                        o[2 * j + 1] -= GAMMA[i] * k * dx;
                    }
                }
                for (row, v) in out.iter_mut().zip(o) {
                    row[l] = v;
                }
            }
        }
    }
    let program = Expression::program(
        6,
        &VORTEX_CODE,
        &VORTEX_A,
        &VORTEX_B,
        &VORTEX_C,
        &VORTEX_OUT,
    )
    .unwrap();
    let mut rng = Rng(11);
    let scene = [1.0, 0.0, -0.5, 0.8, 0.3, -0.9];
    let mu0: Vec<[f64; 6]> = (0..4096)
        .map(|_| std::array::from_fn(|i| scene[i] + rng.range(-0.2, 0.2)))
        .collect();
    let n = 20;
    let mut out = vec![0.0; mu0.len() * 2 * 6];
    let (interpreted, by_hand) = (
        Rk4 {
            system: Program(program),
        },
        Rk4 { system: ByHand },
    );
    let mut g = c.benchmark_group("classical/vortices");
    g.sample_size(10);
    g.warm_up_time(Duration::from_millis(500));
    g.measurement_time(Duration::from_secs(2));
    g.throughput(Throughput::Elements((mu0.len() * n) as u64));
    let isa = Isa::detect();
    g.bench_function(format!("program-{}", isa.name()), |b| {
        let k = Lanes {
            stepper: &interpreted,
            isa,
        };
        b.iter(|| run_kernel(&k, &mu0, 0.05, n, &mut out))
    });
    g.bench_function(format!("by-hand-{}", isa.name()), |b| {
        let k = Lanes {
            stepper: &by_hand,
            isa,
        };
        b.iter(|| run_kernel(&k, &mu0, 0.05, n, &mut out))
    });
    g.finish();
}

/// S of the rigid body's Taylor K = 3 step in the exponential chart, I = (1.5, 2, 2.5):
/// t Σ aᵢ pᵢ² + t³ Σ_{i<j} b_ij pᵢ² pⱼ² (`poisson_rs.taylor.system_taylor_terms`).
const EXP3_A: [f64; 3] = [-1.0 / 3.0, -1.0 / 4.0, -1.0 / 5.0];
/// b₀₁, b₀₂, b₁₂.
const EXP3_B: [f64; 3] = [-1.0 / 2160.0, -1.0 / 675.0, -1.0 / 3600.0];

fn taylor3_exp() -> Polynomial<3> {
    let mut terms: Vec<Monomial<3>> = (0..3)
        .map(|i| Monomial {
            t_power: 1,
            p_powers: std::array::from_fn(|k| if k == i { 2 } else { 0 }),
            coeff: EXP3_A[i],
        })
        .collect();
    for (&(i, j), &coeff) in [(0, 1), (0, 2), (1, 2)].iter().zip(&EXP3_B) {
        terms.push(Monomial {
            t_power: 3,
            p_powers: std::array::from_fn(|k| if k == i || k == j { 2 } else { 0 }),
            coeff,
        });
    }
    Polynomial::new(terms).unwrap()
}

/// The rigid body's Taylor K = 3 step in the exponential chart, written out by hand for
/// [`taylor3_exp`]'s S: the package's start, one Newton update with a fresh Jacobian and one
/// simplified update (the package's solver averages 2.00 updates a step in
/// `benches/step_costs.py`), then the rotation. No convergence test, no failure handling, no
/// lane verdicts: what the step's arithmetic costs when it runs straight through, as a bound
/// for the package's solver, not a stepper.
struct StraightLineExp3;

type M3 = [[f64; 3]; 3];

impl StraightLineExp3 {
    #[inline(always)]
    fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    }

    #[inline(always)]
    fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    #[inline(always)]
    fn apply(m: &M3, v: [f64; 3]) -> [f64; 3] {
        v3!(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
    }

    /// The cofactor inverse (`poisson_rs::stepper::inverse3`'s operations, inlined).
    #[inline(always)]
    fn inverse(m: &M3) -> M3 {
        let (adj, det) = poisson_rs::stepper::adjugate3(m);
        let r = 1.0 / det;
        m3!(|i, j| adj[i][j] * r)
    }

    /// ∇S and S's Hessian at p (t folded into `a`, `b`).
    #[inline(always)]
    fn jet(a: &[f64; 3], b: &[f64; 3], p: [f64; 3]) -> ([f64; 3], M3) {
        let q = [p[0] * p[0], p[1] * p[1], p[2] * p[2]];
        let d = [
            a[0] + b[0] * q[1] + b[1] * q[2],
            a[1] + b[0] * q[0] + b[2] * q[2],
            a[2] + b[1] * q[0] + b[2] * q[1],
        ];
        let g = [2.0 * p[0] * d[0], 2.0 * p[1] * d[1], 2.0 * p[2] * d[2]];
        let (h01, h02, h12) = (
            4.0 * b[0] * p[0] * p[1],
            4.0 * b[1] * p[0] * p[2],
            4.0 * b[2] * p[1] * p[2],
        );
        let h = [
            [2.0 * d[0], h01, h02],
            [h01, 2.0 * d[1], h12],
            [h02, h12, 2.0 * d[2]],
        ];
        (g, h)
    }

    /// c(s) and c'(s) of the exponential chart by its series (|x|² < 1 here).
    #[inline(always)]
    fn c_series(s: f64) -> (f64, f64) {
        let (mut c, mut dc) = (0.0, 0.0);
        for n in (0..12).rev() {
            c = c * s + C_SERIES[n];
            if n >= 1 {
                dc = dc * s + n as f64 * C_SERIES[n];
            }
        }
        (c, dc)
    }

    /// tar(x, p) = p − ½ x×p + c x×(x×p).
    #[inline(always)]
    fn tar(x: [f64; 3], p: [f64; 3]) -> [f64; 3] {
        let xp = Self::cross(x, p);
        let (c, _) = Self::c_series(Self::dot(x, x));
        let u = Self::cross(x, xp);
        v3!(|i| p[i] - 0.5 * xp[i] + c * u[i])
    }

    /// tar and its p-Jacobian ∂T/∂p + ∂T/∂x · hess, with ∂T/∂p = (1 − c s) I − ½ x̂ + c x xᵀ
    /// and ∂T/∂x = ½ p̂ + c (x pᵀ + w I) + v xᵀ, v = 2c′u − 2c p.
    #[inline(always)]
    fn tar_jacobian(x: [f64; 3], p: [f64; 3], h: &M3) -> ([f64; 3], M3) {
        let xp = Self::cross(x, p);
        let s = Self::dot(x, x);
        let (c, dc) = Self::c_series(s);
        let u = Self::cross(x, xp);
        let t = v3!(|i| p[i] - 0.5 * xp[i] + c * u[i]);
        let w = Self::dot(x, p);
        let v = v3!(|i| 2.0 * dc * u[i] - 2.0 * c * p[i]);
        let (diag, cw) = (1.0 - c * s, c * w);
        let (hx, hp) = (v3!(|i| 0.5 * x[i]), v3!(|i| 0.5 * p[i]));
        let jp = [
            [
                c * x[0] * x[0] + diag,
                c * x[0] * x[1] + hx[2],
                c * x[0] * x[2] - hx[1],
            ],
            [
                c * x[1] * x[0] - hx[2],
                c * x[1] * x[1] + diag,
                c * x[1] * x[2] + hx[0],
            ],
            [
                c * x[2] * x[0] + hx[1],
                c * x[2] * x[1] - hx[0],
                c * x[2] * x[2] + diag,
            ],
        ];
        let mut jx = m3!(|r, k| c * x[r] * p[k] + v[r] * x[k]);
        jx[0][0] += cw;
        jx[1][1] += cw;
        jx[2][2] += cw;
        jx[0][1] -= hp[2];
        jx[0][2] += hp[1];
        jx[1][0] += hp[2];
        jx[1][2] -= hp[0];
        jx[2][0] -= hp[1];
        jx[2][1] += hp[0];
        let j = m3!(|r, k| jp[r][k] + jx[r][0] * h[0][k] + jx[r][1] * h[1][k] + jx[r][2] * h[2][k]);
        (t, j)
    }

    #[inline(always)]
    fn step(h: f64, mu: [f64; 3]) -> [f64; 3] {
        let inv_i = [1.0 / 1.5, 1.0 / 2.0, 1.0 / 2.5];
        let t3 = h * h * h;
        let a = v3!(|i| EXP3_A[i] * h);
        let b = v3!(|i| EXP3_B[i] * t3);
        // The package's start: x₀ = −h μ/I and its Hessian diag(−h/I) from −hH, a first-order
        // p₁ and one fixed-point step with ∇S(p₁) linearised at μ.
        let x0 = v3!(|i| -h * mu[i] * inv_i[i]);
        let turn = Self::cross(x0, mu);
        let p1 = v3!(|i| mu[i] + 0.5 * turn[i]);
        let xt = v3!(|i| x0[i] - h * inv_i[i] * (p1[i] - mu[i]));
        let turn = Self::cross(xt, p1);
        let twice = Self::cross(xt, turn);
        let p = v3!(|i| mu[i] + 0.5 * turn[i] - twice[i] / 12.0);
        // Update 1, a fresh Jacobian; update 2, simplified.
        let (x, hess) = Self::jet(&a, &b, p);
        let (t, j) = Self::tar_jacobian(x, p, &hess);
        let inv = Self::inverse(&j);
        let d = Self::apply(&inv, v3!(|i| mu[i] - t[i]));
        let p = v3!(|i| p[i] + d[i]);
        let (x, _) = Self::jet(&a, &b, p);
        let t = Self::tar(x, p);
        let d = Self::apply(&inv, v3!(|i| mu[i] - t[i]));
        let hd = Self::apply(&hess, d);
        let x = v3!(|i| x[i] + hd[i]);
        // μ' = exp(x̂) μ by Rodrigues' coefficients, from their series.
        let s = Self::dot(x, x);
        let (mut sa, mut sb) = (0.0, 0.0);
        for n in (0..10).rev() {
            sa = sa * s + SIN_SERIES[n];
            sb = sb * s + COS_SERIES[n];
        }
        let xm = Self::cross(x, mu);
        let xxm = Self::cross(x, xm);
        v3!(|i| mu[i] + (sa * xm[i] + sb * xxm[i]))
    }
}

impl poisson_rs::lanes::LaneStepper<3> for StraightLineExp3 {
    #[inline(always)]
    fn step_lanes<const L: usize>(&self, h: f64, mu: &mut [[f64; L]; 3]) {
        // Lane by lane, each lane the scalar step: the compiler vectorises the loop, one
        // register a quantity (an iterator over `mu` would hide that it is one loop).
        #[allow(clippy::needless_range_loop)]
        for l in 0..L {
            let next = Self::step(h, [mu[0][l], mu[1][l], mu[2][l]]);
            (mu[0][l], mu[1][l], mu[2][l]) = (next[0], next[1], next[2]);
        }
    }
}

/// The rigid body's Taylor K = 3 step in the exponential chart, 4096 trajectories × 20 steps:
/// the package's lane solver, the same step map written out by hand ([`StraightLineExp3`]),
/// and the package's RK4 in the same lanes, for the ratios. Before timing, the two Taylor
/// rollouts are checked to agree to 1e-13. `cargo bench --bench rollout -- taylor3-exp`.
fn bench_straight_line_taylor(c: &mut Criterion) {
    use poisson_rs::lanes::{Isa, Lanes};
    use poisson_rs::{RigidBody, Rk4};

    let stepper = BisectionStepper::new(
        GeneratingFunction::new(taylor3_exp(), None, 0, MlpInputs::Plain).unwrap(),
        Groupoid::so3(Chart::Exp).unwrap(),
        NewtonOptions::default(),
    );
    let (batch, n) = (4096usize, 20usize);
    let mu0 = initial_states(batch);
    let isa = Isa::detect();
    let by_hand = Lanes {
        stepper: &StraightLineExp3,
        isa,
    };
    let rk4 = Rk4 {
        system: RigidBody::new([1.5, 2.0, 2.5]).unwrap(),
    };
    let rk4 = Lanes { stepper: &rk4, isa };
    let mut out = vec![0.0; batch * 2 * 3];
    let mut reference = vec![0.0; batch * 2 * 3];
    rollout(&stepper, &mu0, H, n, n, &mut reference).unwrap();
    run_kernel(&by_hand, &mu0, H, n, &mut out);
    let worst = out
        .iter()
        .zip(&reference)
        .map(|(a, b)| (a - b).abs() / b.abs().max(1.0))
        .fold(0.0f64, f64::max);
    assert!(
        worst <= 1e-13,
        "the hand-written step is {worst:e} off the package's"
    );
    let mut g = c.benchmark_group("taylor3-exp");
    g.sample_size(10);
    g.warm_up_time(Duration::from_millis(500));
    g.measurement_time(Duration::from_secs(2));
    g.throughput(Throughput::Elements((batch * n) as u64));
    g.bench_function("package", |b| {
        b.iter(|| black_box(rollout(&stepper, black_box(&mu0), H, n, n, &mut out).unwrap()))
    });
    g.bench_function(format!("straight-line-{}", isa.name()), |b| {
        b.iter(|| run_kernel(&by_hand, &mu0, H, n, &mut out))
    });
    g.bench_function(format!("rk4-{}", isa.name()), |b| {
        b.iter(|| run_kernel(&rk4, &mu0, H, n, &mut out))
    });
    g.finish();
}

/// S of the heavy top's Taylor K = 3 step (I = (1, 1.5, 2), mgl χ = (0, 0, 0.981), the
/// exponential chart on se(3)): rows (k, e₁ … e₆) of tᵏ Π pᵢ^eᵢ and their coefficients, from
/// `poisson_rs.taylor.lie_taylor_terms` (S's t² terms vanish).
const TOP3: [([u32; 7], f64); 11] = [
    ([1, 0, 0, 0, 0, 0, 1], -0.981),
    ([1, 0, 0, 2, 0, 0, 0], -0.25),
    ([1, 0, 2, 0, 0, 0, 0], -0.333_333_333_333_333_3),
    ([1, 2, 0, 0, 0, 0, 0], -0.5),
    ([3, 0, 0, 0, 0, 2, 0], -0.040_098_375),
    ([3, 0, 0, 0, 2, 0, 0], -0.026_732_25),
    ([3, 0, 1, 1, 0, 1, 0], 0.013_624_999_999_999_996),
    ([3, 0, 2, 2, 0, 0, 0], -0.001_157_407_407_407_407),
    ([3, 1, 0, 1, 1, 0, 0], 0.027_249_999_999_999_996),
    ([3, 2, 0, 2, 0, 0, 0], -0.006_944_444_444_444_444),
    ([3, 2, 2, 0, 0, 0, 0], -0.002_314_814_814_814_815),
];

/// The heavy top's Taylor K = 3 step (the package's exponential-chart lane solver on se(3)) and
/// its RK4 in lanes, 4096 trajectories (|M| up to √3, Γ a unit vector) × 20 steps of h = 0.1.
/// `cargo bench --bench rollout -- taylor3-heavy-top`.
fn bench_heavy_top_taylor(c: &mut Criterion) {
    use poisson_rs::lanes::{Isa, Lanes};
    use poisson_rs::{LieAlgebra, LiePoisson, Rk4};

    let terms = TOP3
        .iter()
        .map(|&(e, coeff)| Monomial {
            t_power: e[0],
            p_powers: std::array::from_fn(|i| e[1 + i]),
            coeff,
        })
        .collect();
    let stepper = BisectionStepper::new(
        GeneratingFunction::new(
            Polynomial::<6>::new(terms).unwrap(),
            None,
            0,
            MlpInputs::Plain,
        )
        .unwrap(),
        Groupoid::new(LieAlgebra::se3(), Chart::Exp).unwrap(),
        NewtonOptions::default(),
    );
    let top = LiePoisson::heavy_top([1.0, 1.5, 2.0], [0.0, 0.0, 0.981]).unwrap();
    let rk4 = Rk4 {
        system: poisson_rs::straight_line::LieField::new(&top),
    };
    let isa = Isa::detect();
    let rk4 = Lanes { stepper: &rk4, isa };
    let mut rng = Rng(11);
    let mu0: Vec<[f64; 6]> = (0..4096)
        .map(|_| {
            let m: [f64; 3] = std::array::from_fn(|_| rng.range(-1.0, 1.0));
            let g = rng.sphere(1.0);
            [m[0], m[1], m[2], g[0], g[1], g[2]]
        })
        .collect();
    let n = 20;
    let mut out = vec![0.0; mu0.len() * 2 * 6];
    let mut reference = out.clone();
    // The table is the heavy top's S: its steps stay within 1e-3 of RK4's after 20 steps (3.4e-5
    // measured through `pr.integrate`; a wrong t¹ coefficient is off by about 1e-1).
    rollout(&stepper, &mu0, H, n, n, &mut out).unwrap();
    run_kernel(&rk4, &mu0, H, n, &mut reference);
    let worst = out
        .iter()
        .zip(&reference)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(worst <= 1e-3, "the Taylor step is {worst:e} off RK4's");
    let mut g = c.benchmark_group("taylor3-heavy-top");
    g.sample_size(10);
    g.warm_up_time(Duration::from_millis(500));
    g.measurement_time(Duration::from_secs(3));
    g.throughput(Throughput::Elements((mu0.len() * n) as u64));
    g.bench_function("package", |b| {
        b.iter(|| black_box(rollout(&stepper, black_box(&mu0), H, n, n, &mut out).unwrap()))
    });
    g.bench_function(format!("rk4-{}", isa.name()), |b| {
        b.iter(|| run_kernel(&rk4, &mu0, H, n, &mut out))
    });
    g.finish();
}

criterion_group!(
    benches,
    bench_heavy_top_taylor,
    bench_straight_line_taylor,
    bench_classical,
    bench_expression_field,
    bench_splitting_lanes,
    bench_bisection_lanes,
    bench_rollout,
    bench_step,
    bench_kernel,
    bench_paper
);
criterion_main!(benches);
