//! Scratch memory for the evaluations of a generating function.

use super::{GeneratingFunction, LaneRow, Mlp, MAX_BATCH};
use crate::dual::{Dual1, Jet2, Variable};
use crate::isa::LANES;

/// Scratch memory for one evaluation at a time; allocated once per worker, never per step.
#[derive(Clone, Debug)]
pub struct Workspace<const N: usize> {
    pub(super) jet_a: Vec<Jet2<N>>,
    pub(super) jet_b: Vec<Jet2<N>>,
    pub(super) d1_a: Vec<Dual1<N>>,
    pub(super) d1_b: Vec<Dual1<N>>,
    /// Two (widest layer × COMPONENTS·MAX_BATCH) activation buffers for batched passes.
    pub(super) batch_a: Vec<f64>,
    pub(super) batch_b: Vec<f64>,
    /// Every layer's activations for MAX_BATCH trajectories, kept for the reverse pass.
    pub(super) acts: Vec<f64>,
    /// Two layers' jets in lanes, for the lane Newton solvers' network term
    /// ([`super::NetworkLanes`]); empty where S has no network term that fits the lanes.
    pub(crate) lanes: Vec<LaneRow>,
}

impl<const N: usize> Workspace<N> {
    /// Bytes a workspace for `generating` takes, computed without allocating it (the bindings
    /// check it against the memory available before a rollout creates one per thread).
    pub fn bytes(generating: &GeneratingFunction<N>) -> usize {
        let (singles, batch, acts) = Self::sizes(generating);
        singles
            .saturating_mul(
                2 * std::mem::size_of::<Jet2<N>>() + 2 * std::mem::size_of::<Dual1<N>>(),
            )
            .saturating_add(batch.saturating_mul(16))
            .saturating_add(acts.saturating_mul(8))
            .saturating_add(Self::lane_len(generating).saturating_mul(8 * LANES))
    }

    /// Rows of the lane scratch: [`super::scratch_len`] where the network term fits the lanes,
    /// else none.
    pub(super) fn lane_len(generating: &GeneratingFunction<N>) -> usize {
        generating
            .network_lanes()
            .map_or(0, |net| super::scratch_len(net.mlp, N))
    }

    /// Elements of the single-trajectory buffers, of each batch buffer, and of `acts`.
    pub(super) fn sizes(generating: &GeneratingFunction<N>) -> (usize, usize, usize) {
        let mlp = generating.mlp.as_ref();
        let w = mlp.map_or(0, Mlp::max_width).max(N + 1);
        let batch = if mlp.is_some() {
            w.saturating_mul(<Jet2<N> as Variable<N>>::COMPONENTS)
                .saturating_mul(MAX_BATCH)
        } else {
            0
        };
        let acts = mlp
            .map_or(0, Mlp::activation_rows)
            .saturating_mul(MAX_BATCH);
        (w, batch, acts)
    }
}
