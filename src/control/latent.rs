//! Closed-loop policies: latent PD on encoded frames (each frame encoded once), and the oracle
//! PD on the true state.

use std::time::Instant;

use burn::tensor::Device;

use super::PdController;
use crate::envs::State;
use crate::model::{Encoder, frames_to_tensor, to_vec};

/// A controller in the closed loop: sees the frame (and, for the oracle only, the true state).
pub trait Policy {
    /// Starts an episode toward the goal image (`goal` is the true goal state, for the oracle
    /// only, as `act`'s `state` is).
    fn reset(&mut self, goal_frame: &[u8], goal: &State);
    /// The action for the newest frame; `u` has the action dimension.
    fn act(&mut self, frame: &[u8], state: &State, u: &mut [f64]);
    /// The latent configuration `h` of the last frame seen (empty for the oracle).
    fn latent(&self) -> Vec<f64>;
    /// The goal's latent configuration (empty for the oracle).
    fn goal_latent(&self) -> Vec<f64>;
}

/// PD on the learned latent: `h = e(frame)`, `v = (h - h_prev)/dt`, goal `h* = e(goal)`, `v* = 0`.
pub struct LatentPdPolicy {
    encoder: Encoder,
    device: Device,
    pd: PdController,
    dt: f64,
    h_goal: Vec<f64>,
    /// Encoding of the previous frame (`None` at the start of an episode).
    h_prev: Option<Vec<f64>>,
    h: Vec<f64>,
    /// Number of frames encoded so far (each frame exactly once).
    pub frames_encoded: usize,
    /// Wall time of each `act` call (encode + PD), seconds.
    pub control_times_s: Vec<f64>,
}

impl LatentPdPolicy {
    pub fn new(encoder: Encoder, device: Device, pd: PdController, dt: f64) -> Self {
        Self {
            encoder,
            device,
            pd,
            dt,
            h_goal: vec![],
            h_prev: None,
            h: vec![],
            frames_encoded: 0,
            control_times_s: vec![],
        }
    }

    /// Encodes one frame to `h`.
    pub fn encode(&mut self, frame: &[u8]) -> Vec<f64> {
        self.frames_encoded += 1;
        let h = self
            .encoder
            .forward(frames_to_tensor(std::iter::once(frame), &self.device));
        to_vec(h).into_iter().map(f64::from).collect()
    }
}

impl Policy for LatentPdPolicy {
    fn reset(&mut self, goal_frame: &[u8], _goal: &State) {
        self.h_goal = self.encode(goal_frame);
        self.h_prev = None;
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
        let zeros = vec![0.0; h.len()];
        self.pd.control(&h, &v, &self.h_goal, &zeros, u);
        self.h_prev = Some(h.clone());
        self.h = h;
        self.control_times_s.push(start.elapsed().as_secs_f64());
    }

    fn latent(&self) -> Vec<f64> {
        self.h.clone()
    }
    fn goal_latent(&self) -> Vec<f64> {
        self.h_goal.clone()
    }
}

/// PD on the true state: the upper bound any latent controller is measured against.
pub struct OraclePdPolicy {
    pd: PdController,
    goal: Vec<f64>,
}

impl OraclePdPolicy {
    /// The goal comes with each episode's `reset`.
    pub fn new(pd: PdController) -> Self {
        Self { pd, goal: vec![] }
    }
}

impl Policy for OraclePdPolicy {
    fn reset(&mut self, _goal_frame: &[u8], goal: &State) {
        self.goal = goal.q.clone();
    }
    fn act(&mut self, _frame: &[u8], state: &State, u: &mut [f64]) {
        let zeros = vec![0.0; state.q.len()];
        self.pd.control(&state.q, &state.qd, &self.goal, &zeros, u);
    }
    fn latent(&self) -> Vec<f64> {
        vec![]
    }
    fn goal_latent(&self) -> Vec<f64> {
        vec![]
    }
}
