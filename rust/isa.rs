//! What SIMD code runs with: the lane width of a block ([`LANES`]) and the instruction set
//! ([`Isa`]), detected once at run time. Every module with lane kernels (the classical lanes, the
//! polynomial jets of a generating function, the so(3) Newton lanes) takes both from here.

/// Lanes per block: 8 f64, two AVX2 registers (or four SSE2 ones) per coordinate, which gives the
/// core independent chains to overlap; 4 was slower (see docs/performance.md).
pub const LANES: usize = 8;

/// The most coordinates at which a block pays to run compiled for AVX-512 ([`Isa::is_avx512`]):
/// the default of every lane stepper and Newton solve (`LaneStepper::AVX512`, `LaneField::AVX512`,
/// `LaneSolve::avx512`). Measured (`benches/step_costs.py`, docs/performance.md): at N ≤ 3 the
/// blocks took 0.75–0.97× their AVX2 time; at N ≥ 5 every one lost (the heavy top's RK4 2.3×,
/// its se(3) solve 1.8–2.0×, 5-D Lotka–Volterra's RK4 2.4×), the compiler mixing lanes and
/// coordinates in its shuffles there.
pub const AVX512_MAX_DIM: usize = 3;

/// The instruction set a block loop runs with, as a proof about this CPU: the portable baseline
/// ([`Isa::PORTABLE`], which every CPU runs), AVX2 with FMA, which only [`Isa::detect`] and
/// [`Isa::avx2`] can return, and only where the CPU runs both, or that with AVX-512 (F and VL),
/// from [`Isa::detect`] and [`Isa::avx512`] only. The fields are private, so safe code cannot
/// claim a feature on a CPU without it: the safe functions that take an `Isa`
/// ([`crate::lanes::Lanes`], [`crate::generating::polynomial_lanes::polynomial_jets`], …) call
/// code compiled for the features it names, which on a CPU without them would be undefined
/// behaviour.
///
/// ```
/// use poisson_rs::isa::Isa;
/// let isa = Isa::detect();
/// assert!(isa == Isa::PORTABLE || Isa::avx2() == Some(isa) || Isa::avx512() == Some(isa));
/// assert!(!isa.is_avx512() || isa.is_avx2());
/// ```
///
/// The AVX2 proof cannot be written by hand:
///
/// ```compile_fail
/// use poisson_rs::isa::Isa;
/// let forged = Isa { avx2: true, avx512: false };
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Isa {
    /// AVX2 and FMA (x86-64 only; FMA is enabled but never contracted into, see
    /// [`crate::lanes`]). True only where run-time detection found both.
    avx2: bool,
    /// AVX-512 F and VL besides AVX2 and FMA: true only where detection found all four.
    avx512: bool,
}

impl Isa {
    /// The target's baseline (SSE2 on x86-64): runs everywhere.
    pub const PORTABLE: Isa = Isa {
        avx2: false,
        avx512: false,
    };

    /// AVX2 with FMA, where this CPU runs both; None elsewhere. With [`Isa::detect`], the only
    /// way to obtain an `Isa` that claims them.
    pub fn avx2() -> Option<Isa> {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                return Some(Isa {
                    avx2: true,
                    avx512: false,
                });
            }
        }
        None
    }

    /// AVX-512 F and VL with AVX2 and FMA, where this CPU runs all four; None elsewhere. Code
    /// that asks only [`Isa::is_avx2`] takes its AVX2 path with it.
    pub fn avx512() -> Option<Isa> {
        #[cfg(target_arch = "x86_64")]
        {
            if Isa::avx2().is_some()
                && std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512vl")
            {
                return Some(Isa {
                    avx2: true,
                    avx512: true,
                });
            }
        }
        None
    }

    /// The widest instruction set this CPU runs.
    pub fn detect() -> Isa {
        Isa::avx512().or_else(Isa::avx2).unwrap_or(Isa::PORTABLE)
    }

    /// Whether this is the AVX2 proof: code compiled with `#[target_feature(enable =
    /// "avx2,fma")]` may then run.
    pub fn is_avx2(self) -> bool {
        self.avx2
    }

    /// Whether this is the AVX-512 proof: code compiled with `#[target_feature(enable =
    /// "avx512f,avx512vl,avx2,fma")]` may then run.
    pub fn is_avx512(self) -> bool {
        self.avx512
    }

    pub fn name(self) -> &'static str {
        match (self.avx2, self.avx512) {
            (_, true) => "avx512+avx2+fma",
            (true, false) => "avx2+fma",
            (false, false) => "portable",
        }
    }
}
