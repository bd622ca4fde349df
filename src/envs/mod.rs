//! Simulated pixel environments: one trait, one step loop, physics and rendering kept apart.
//! Point mass and reacher are drawn top-down in 2D (`render2d`); Fetch is ray cast in 3D
//! (`render3d`).

mod fetch;
mod fetch_arm;
mod mujoco;
mod point_mass;
mod reacher;
mod render2d;
mod render3d;

pub use fetch::{ARM_LABEL, Fetch, FetchConfig, GRIPPER_LABEL, TABLE_LABEL};
pub use fetch_arm::{
    ARM_JOINTS, ArmJoint, ArmPose, FETCH_ARM, GRIP_SITE_OFFSET_M, GRIPPER_DOWN, GRIPPER_OFFSET_M,
    IkConfig, IkSolution, LinkFrame, RESET_Q, forward_kinematics,
};
pub use mujoco::SoftLimitModel;
pub use point_mass::{PointMass, PointMassConfig};
pub use reacher::{Reacher, ReacherConfig};
pub use render2d::TopDownCamera;
pub use render3d::{Lighting, Mat3, OrbitCamera, Picked, Vec3};

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::{Error, Result};

/// Observation side length in pixels: every environment renders 64x64 RGB.
pub const FRAME_PX: usize = 64;
/// Bytes in one observation (`FRAME_PX * FRAME_PX * 3`, row-major, RGB).
pub const FRAME_BYTES: usize = FRAME_PX * FRAME_PX * 3;

/// One rendered observation: 64x64 RGB, u8, row 0 at the top.
pub type Frame = [u8; FRAME_BYTES];

/// The environments procl knows, by their command-line names.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EnvKind {
    /// Point mass-2D (dm_control `point_mass`).
    PointMass,
    /// Reacher-2D (dm_control `reacher` with NewtonianVAE's joint ranges).
    Reacher,
    /// Fetch-3D (gym `FetchReach` with end-effector acceleration control).
    Fetch,
}

impl EnvKind {
    /// Command-line names of all environments.
    pub const NAMES: &'static [&'static str] = &["point-mass", "reacher", "fetch"];

    /// The command-line name.
    pub fn name(self) -> &'static str {
        match self {
            EnvKind::PointMass => "point-mass",
            EnvKind::Reacher => "reacher",
            EnvKind::Fetch => "fetch",
        }
    }

    /// Builds the environment with its default configuration.
    pub fn make(self) -> Box<dyn Env> {
        match self {
            EnvKind::PointMass => Box::new(PointMass::new(PointMassConfig::default())),
            EnvKind::Reacher => Box::new(Reacher::new(ReacherConfig::default())),
            EnvKind::Fetch => Box::new(Fetch::new(FetchConfig::default())),
        }
    }
}

impl std::str::FromStr for EnvKind {
    type Err = Error;
    fn from_str(name: &str) -> Result<Self> {
        match name {
            "point-mass" | "point_mass" | "pointmass" => Ok(EnvKind::PointMass),
            "reacher" => Ok(EnvKind::Reacher),
            "fetch" | "fetch-3d" | "fetch-reach" => Ok(EnvKind::Fetch),
            other => Err(Error::UnknownEnv {
                name: other.to_string(),
                known: EnvKind::NAMES.join(", "),
            }),
        }
    }
}

impl std::fmt::Display for EnvKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Name of a data source that is none of procl's environments (frames from elsewhere).
pub const CUSTOM_SOURCE: &str = "custom";

/// The name of an optional environment: its own, or [`CUSTOM_SOURCE`] for data from elsewhere.
pub fn source_name(env: Option<EnvKind>) -> &'static str {
    env.map_or(CUSTOM_SOURCE, EnvKind::name)
}

/// Serde for `Option<EnvKind>` as one string: an environment's name, or `custom` for `None`
/// (datasets and runs of systems procl does not simulate).
pub mod env_or_custom {
    use super::{CUSTOM_SOURCE, EnvKind, source_name};

    pub fn serialize<S: serde::Serializer>(
        env: &Option<EnvKind>,
        serializer: S,
    ) -> std::result::Result<S::Ok, S::Error> {
        serializer.serialize_str(source_name(*env))
    }

    pub fn deserialize<'de, D: serde::Deserializer<'de>>(
        deserializer: D,
    ) -> std::result::Result<Option<EnvKind>, D::Error> {
        let name: String = serde::Deserialize::deserialize(deserializer)?;
        if name == CUSTOM_SOURCE {
            return Ok(None);
        }
        name.parse::<EnvKind>().map(Some).map_err(|_| {
            serde::de::Error::custom(format!(
                "unknown environment `{name}` (expected {}, or {CUSTOM_SOURCE})",
                EnvKind::NAMES.join(", ")
            ))
        })
    }
}

/// The true physical state: configuration `q` and its velocity `qd` (SI units).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct State {
    /// Configuration (m for slide joints, rad for hinges).
    pub q: Vec<f64>,
    /// Velocity of the configuration.
    pub qd: Vec<f64>,
}

impl State {
    /// `q` followed by `qd`, the layout of the dataset's `states` array.
    pub fn to_vec(&self) -> Vec<f64> {
        self.q.iter().chain(&self.qd).copied().collect()
    }
}

/// A simulated system that is controlled and observed through pixels.
///
/// Observations never show a goal marker: goals are given as images rendered at the goal state
/// (`set_state` then `render`). Same seed, same trajectory, same pixels, bit for bit.
pub trait Env: Send {
    /// Which environment this is.
    fn kind(&self) -> EnvKind;
    /// Control period in seconds (one action per period).
    fn control_dt_s(&self) -> f64;
    /// Number of action dimensions; every action component is bounded to [-1, 1].
    fn action_dim(&self) -> usize;
    /// Number of configuration dimensions (`q`); `qd` has the same length.
    fn config_dim(&self) -> usize;
    /// The current true state.
    fn state(&self) -> State;
    /// Sets the state; fails on a wrong length or a non-finite entry.
    fn set_state(&mut self, state: &State) -> Result<()>;
    /// The configuration box (joint ranges), one `[lo, hi]` per configuration dimension.
    fn config_ranges(&self) -> Vec<[f64; 2]>;
    /// A configuration drawn uniformly over the configuration space (the joint ranges).
    fn sample_config(&self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        sample_box(rng, &self.config_ranges())
    }
    /// Advances one control period under `action` (clipped to [-1, 1]; NaN counts as 0).
    fn step(&mut self, action: &[f64]);
    /// Renders the current state into `frame`.
    fn render(&mut self, frame: &mut Frame);
    /// Distance between two configurations in the units the evaluation reports.
    fn config_distance(&self, a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f64>()
            .sqrt()
    }
    /// Distance (m) between the fingertip's positions at two configurations, for an env whose
    /// configuration distance is not already one in metres: the reacher (the paper reports it
    /// beside the joint-space distance). `None` elsewhere.
    fn fingertip_distance_m(&self, _a: &[f64], _b: &[f64]) -> Option<f64> {
        None
    }

    /// Starts an episode from a seeded random configuration at rest.
    fn reset(&mut self, seed: u64) -> Result<()> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let q = self.sample_config(&mut rng);
        let qd = vec![0.0; q.len()];
        self.set_state(&State { q, qd })
    }
}

/// Clips an action to [-1, 1] per component; a non-finite component becomes 0 so bad controller
/// output can never inject NaN into the physics.
pub fn clip_action<const N: usize>(action: &[f64]) -> [f64; N] {
    std::array::from_fn(|i| {
        let a = action.get(i).copied().unwrap_or(0.0);
        if a.is_finite() {
            a.clamp(-1.0, 1.0)
        } else {
            0.0
        }
    })
}

/// Checks a state's lengths and finiteness for an environment with `dim` dofs.
pub(crate) fn validate_state(env: &'static str, state: &State, dim: usize) -> Result<()> {
    if state.q.len() != dim || state.qd.len() != dim {
        return Err(Error::InvalidState {
            env,
            message: format!(
                "expected q and qd of length {dim}, got {} and {}",
                state.q.len(),
                state.qd.len()
            ),
        });
    }
    if !state.q.iter().chain(&state.qd).all(|x| x.is_finite()) {
        return Err(Error::InvalidState {
            env,
            message: "non-finite entry".into(),
        });
    }
    Ok(())
}

/// Uniform sample in `[lo, hi]` per component.
pub(crate) fn sample_box(rng: &mut ChaCha8Rng, ranges: &[[f64; 2]]) -> Vec<f64> {
    ranges
        .iter()
        .map(|&[lo, hi]| rng.random_range(lo..=hi))
        .collect()
}
