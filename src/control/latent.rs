//! Closed-loop policies: a feedback law (PD, PID) on encoded frames (each frame encoded once),
//! and the oracle PD on the true state.

use std::time::Instant;

use burn::tensor::Device;

use super::{FeedbackLaw, PdController};
use crate::envs::State;
use crate::model::{Encoder, HostEncoder, LatentEncoder, frames_to_tensor, to_vec};

/// A tracking target for the next action: the reference's latent `(h*, v*)` for latent
/// policies, its true state for the oracle.
pub struct Target<'a> {
    pub h: &'a [f64],
    pub v: &'a [f64],
    pub state: &'a State,
}

/// A controller in the closed loop: sees the frame (and, for the oracle only, the true state).
pub trait Policy {
    /// Starts an episode toward the goal image (`goal` is the true goal state, for the oracle
    /// only, as `act`'s `state` is): the target is the goal at rest.
    fn reset(&mut self, goal_frame: &[u8], goal: &State);
    /// Starts a tracking episode (forgets the previous frame); targets come from `set_target`.
    fn start_tracking(&mut self);
    /// Sets the target of the next `act` (tracking).
    fn set_target(&mut self, target: &Target<'_>);
    /// The action for the newest frame; `u` has the action dimension.
    fn act(&mut self, frame: &[u8], state: &State, u: &mut [f64]);
    /// The latent configuration `h` of the last frame seen (empty for the oracle).
    fn latent(&self) -> Vec<f64>;
    /// The goal's latent configuration (empty for the oracle).
    fn goal_latent(&self) -> Vec<f64>;
}

/// A feedback law on a learned latent: `h = e(frame)`, `v = (h - h_prev)/dt`; for reaching the
/// target is `h* = e(goal)`, `v* = 0`, for tracking the reference's encoding and its finite
/// difference.
pub struct LatentPolicy<L, E = Encoder> {
    encoder: E,
    /// The encoder's host copy, where it has one: one frame at a time without tensors.
    host: Option<HostEncoder>,
    device: Device,
    law: L,
    dt: f64,
    h_target: Vec<f64>,
    v_target: Vec<f64>,
    /// Encoding of the previous frame (`None` at the start of an episode).
    h_prev: Option<Vec<f64>>,
    h: Vec<f64>,
    /// Number of frames encoded so far (each frame exactly once).
    pub frames_encoded: usize,
    /// Wall time of each `act` call (encode + feedback law), seconds.
    pub control_times_s: Vec<f64>,
}

/// Latent PD on ProCL's (or PC3's) encoder.
pub type LatentPdPolicy = LatentPolicy<PdController>;

impl<L: FeedbackLaw, E: LatentEncoder> LatentPolicy<L, E> {
    pub fn new(encoder: E, device: Device, law: L, dt: f64) -> Self {
        Self {
            host: encoder.host_encoder(),
            encoder,
            device,
            law,
            dt,
            h_target: vec![],
            v_target: vec![],
            h_prev: None,
            h: vec![],
            frames_encoded: 0,
            control_times_s: vec![],
        }
    }

    /// The encoder the policy sees frames through.
    pub fn encoder(&self) -> &E {
        &self.encoder
    }

    /// Encodes one frame to `h`.
    pub fn encode(&mut self, frame: &[u8]) -> Vec<f64> {
        self.frames_encoded += 1;
        if let Some(host) = self.host.as_mut() {
            let mut h = vec![0.0; host.latent_dim()];
            host.encode(frame, &mut h);
            return h;
        }
        let h = self
            .encoder
            .encode(frames_to_tensor(std::iter::once(frame), &self.device));
        to_vec(h).into_iter().map(f64::from).collect()
    }
}

impl<L: FeedbackLaw, E: LatentEncoder> Policy for LatentPolicy<L, E> {
    fn reset(&mut self, goal_frame: &[u8], _goal: &State) {
        self.h_target = self.encode(goal_frame);
        self.v_target = vec![0.0; self.h_target.len()];
        self.h_prev = None;
        self.law.reset();
    }

    fn start_tracking(&mut self) {
        self.h_prev = None;
        self.law.reset();
    }

    fn set_target(&mut self, target: &Target<'_>) {
        self.h_target.clear();
        self.h_target.extend_from_slice(target.h);
        self.v_target.clear();
        self.v_target.extend_from_slice(target.v);
    }

    fn act(&mut self, frame: &[u8], _state: &State, u: &mut [f64]) {
        let start = Instant::now();
        // Only the new frame is encoded; the previous encoding is cached. Episodes start at
        // rest, so the first velocity estimate is 0.
        let h = self.encode(frame);
        let v: Vec<f64> = match &self.h_prev {
            Some(prev) => h.iter().zip(prev).map(|(a, b)| (a - b) / self.dt).collect(),
            None => vec![0.0; h.len()],
        };
        self.law.feedback(&h, &v, &self.h_target, &self.v_target, u);
        self.h_prev = Some(h.clone());
        self.h = h;
        self.control_times_s.push(start.elapsed().as_secs_f64());
    }

    fn latent(&self) -> Vec<f64> {
        self.h.clone()
    }
    fn goal_latent(&self) -> Vec<f64> {
        self.h_target.clone()
    }
}

/// PD on the true state: the upper bound any latent controller is measured against.
pub struct OraclePdPolicy {
    pd: PdController,
    target: State,
}

impl OraclePdPolicy {
    /// The goal comes with each episode's `reset`.
    pub fn new(pd: PdController) -> Self {
        Self {
            pd,
            target: State {
                q: vec![],
                qd: vec![],
            },
        }
    }
}

impl Policy for OraclePdPolicy {
    fn reset(&mut self, _goal_frame: &[u8], goal: &State) {
        self.target = State {
            q: goal.q.clone(),
            qd: vec![0.0; goal.q.len()],
        };
    }
    fn start_tracking(&mut self) {}
    fn set_target(&mut self, target: &Target<'_>) {
        self.target = target.state.clone();
    }
    fn act(&mut self, _frame: &[u8], state: &State, u: &mut [f64]) {
        let target = &self.target;
        self.pd
            .control(&state.q, &state.qd, &target.q, &target.qd, u);
    }
    fn latent(&self) -> Vec<f64> {
        vec![]
    }
    fn goal_latent(&self) -> Vec<f64> {
        vec![]
    }
}
