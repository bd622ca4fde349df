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
        EnvConfig::from(self).make()
    }
}

/// One environment with its whole configuration. A variant of an environment (the arm's base
/// moved, other link lengths or colours) is its kind with other parameters; datasets collected
/// from a variant record it, and runs trained on them are evaluated in it.
///
/// As TOML, one table named after the environment with the fields that differ from its
/// defaults, e.g. `[reacher]` and `base_m = [0.035, -0.025]`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum EnvConfig {
    PointMass(PointMassConfig),
    Reacher(ReacherConfig),
    Fetch(FetchConfig),
}

impl From<EnvKind> for EnvConfig {
    fn from(kind: EnvKind) -> Self {
        match kind {
            EnvKind::PointMass => EnvConfig::PointMass(PointMassConfig::default()),
            EnvKind::Reacher => EnvConfig::Reacher(ReacherConfig::default()),
            EnvKind::Fetch => EnvConfig::Fetch(FetchConfig::default()),
        }
    }
}

impl EnvConfig {
    /// Which environment this configures.
    pub fn kind(&self) -> EnvKind {
        match self {
            EnvConfig::PointMass(_) => EnvKind::PointMass,
            EnvConfig::Reacher(_) => EnvKind::Reacher,
            EnvConfig::Fetch(_) => EnvKind::Fetch,
        }
    }

    /// Whether this is the environment's default configuration.
    pub fn is_default(&self) -> bool {
        *self == EnvConfig::from(self.kind())
    }

    /// Builds the environment.
    pub fn make(&self) -> Box<dyn Env> {
        match self {
            EnvConfig::PointMass(config) => Box::new(PointMass::new(config.clone())),
            EnvConfig::Reacher(config) => Box::new(Reacher::new(config.clone())),
            EnvConfig::Fetch(config) => Box::new(Fetch::new(config.clone())),
        }
    }

    /// Refuses parameters the simulator cannot run or the camera cannot draw, naming the field.
    pub fn validate(&self) -> Result<()> {
        let fields = FieldCheck(self.kind());
        match self {
            EnvConfig::PointMass(c) => {
                fields.positive("control_dt_s", c.control_dt_s)?;
                fields.positive("mass_kg", c.mass_kg)?;
                fields.non_negative("damping", c.damping)?;
                fields.positive("gear", c.gear)?;
                fields.positive("joint_limit_m", c.joint_limit_m)?;
                fields.positive("ball_radius_m", c.ball_radius_m)?;
                fields.soft_limits(&c.soft_limits)?;
                fields.colour("ball_rgb", c.ball_rgb)?;
                fields.top_down_camera(&c.camera)
            }
            EnvConfig::Reacher(c) => c.validate(),
            EnvConfig::Fetch(c) => {
                fields.positive("control_dt_s", c.control_dt_s)?;
                fields.positive("max_accel_m_s2", c.max_accel_m_s2)?;
                let (lo, hi) = (c.workspace_lo_m, c.workspace_hi_m);
                if !(0..3).all(|i| lo[i].is_finite() && hi[i].is_finite() && lo[i] < hi[i]) {
                    return Err(Error::config(
                        "fetch.workspace_lo_m",
                        format!("{lo:?} must lie below workspace_hi_m {hi:?} on every axis"),
                    ));
                }
                fields.finite("initial_grip_m", &c.initial_grip_m)?;
                fields.non_negative(
                    "ik.orientation_weight_m_per_rad",
                    c.ik.orientation_weight_m_per_rad,
                )?;
                fields
                    .non_negative("ik.posture_weight_m_per_rad", c.ik.posture_weight_m_per_rad)?;
                fields.non_negative(
                    "ik.elbow_roll_weight_m_per_rad",
                    c.ik.elbow_roll_weight_m_per_rad,
                )?;
                fields.at_least("ik.max_iterations", c.ik.max_iterations, 1)?;
                fields.orbit_camera(&c.camera)?;
                fields.lighting(&c.lighting)?;
                fields.at_least("samples_per_axis", c.samples_per_axis, 1)?;
                for (field, rgb) in [
                    ("floor_rgb", c.floor_rgb),
                    ("table_rgb", c.table_rgb),
                    ("sky_rgb", c.sky_rgb),
                    ("robot_rgb", c.robot_rgb),
                    ("arm_white_rgb", c.arm_white_rgb),
                    ("arm_blue_rgb", c.arm_blue_rgb),
                    ("gripper_rgb", c.gripper_rgb),
                ] {
                    fields.colour(field, rgb)?;
                }
                Ok(())
            }
        }
    }

    /// Reads a configuration file: one TOML table named after an environment (`[reacher]`,
    /// `[point-mass]`, `[fetch]`) holding the fields that differ from its defaults.
    pub fn load(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let config: Self = toml::from_str(&text).map_err(|e| {
            Error::config(
                path.display().to_string(),
                format!(
                    "not an environment configuration ({}); expected one table, [{}], with the fields to change",
                    e.message(),
                    EnvKind::NAMES.join("] or [")
                ),
            )
        })?;
        config.validate()?;
        Ok(config)
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

/// The checks of one environment's configuration fields: each refusal names `env.field`.
pub(crate) struct FieldCheck(pub(crate) EnvKind);

impl FieldCheck {
    fn refuse(&self, field: &str, why: String) -> Result<()> {
        Err(Error::config(format!("{}.{field}", self.0), why))
    }

    pub(crate) fn positive(&self, field: &str, value: f64) -> Result<()> {
        if value.is_finite() && value > 0.0 {
            Ok(())
        } else {
            self.refuse(field, format!("{value} must be positive"))
        }
    }

    pub(crate) fn non_negative(&self, field: &str, value: f64) -> Result<()> {
        if value.is_finite() && value >= 0.0 {
            Ok(())
        } else {
            self.refuse(field, format!("{value} must be >= 0"))
        }
    }

    fn at_least(&self, field: &str, value: usize, least: usize) -> Result<()> {
        if value >= least {
            Ok(())
        } else {
            self.refuse(field, format!("{value} must be at least {least}"))
        }
    }

    fn finite(&self, field: &str, values: &[f64]) -> Result<()> {
        if values.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            self.refuse(field, format!("{values:?} must be finite"))
        }
    }

    /// Strictly between `lo` and `hi`.
    fn inside(&self, field: &str, value: f64, lo: f64, hi: f64) -> Result<()> {
        if value > lo && value < hi {
            Ok(())
        } else {
            self.refuse(
                field,
                format!("{value} must lie strictly between {lo} and {hi}"),
            )
        }
    }

    pub(crate) fn colour(&self, field: &str, rgb: [f32; 3]) -> Result<()> {
        if rgb.iter().all(|c| (0.0..=1.0).contains(c)) {
            Ok(())
        } else {
            self.refuse(field, format!("{rgb:?} is not an RGB colour in [0, 1]"))
        }
    }

    /// MuJoCo's ranges for `solref` and `solimp`.
    pub(crate) fn soft_limits(&self, limits: &SoftLimitModel) -> Result<()> {
        let [dmin, dmax, width, midpoint, power] = limits.solimp;
        self.positive("soft_limits.timeconst_s", limits.timeconst_s)?;
        self.positive("soft_limits.dampratio", limits.dampratio)?;
        for impedance in [dmin, dmax] {
            self.inside("soft_limits.solimp", impedance, 0.0, 1.0)?;
        }
        self.positive("soft_limits.solimp", width)?;
        self.inside("soft_limits.solimp", midpoint, 0.0, 1.0)?;
        if power.is_finite() && power >= 1.0 {
            Ok(())
        } else {
            self.refuse("soft_limits.solimp", format!("power {power} must be >= 1"))
        }
    }

    pub(crate) fn top_down_camera(&self, camera: &TopDownCamera) -> Result<()> {
        self.positive("camera.height_m", camera.height_m)?;
        self.inside("camera.fovy_deg", camera.fovy_deg, 0.0, 180.0)?;
        self.positive("camera.checker_m", camera.checker_m)
    }

    fn orbit_camera(&self, camera: &OrbitCamera) -> Result<()> {
        self.positive("camera.distance_m", camera.distance_m)?;
        self.finite("camera.azimuth_deg", &[camera.azimuth_deg])?;
        self.finite("camera.elevation_deg", &[camera.elevation_deg])?;
        self.finite("camera.lookat_m", &camera.lookat_m)?;
        self.inside("camera.fovy_deg", camera.fovy_deg, 0.0, 180.0)?;
        // The observation is a 64x64 crop of the full render.
        self.at_least("camera.full_render_px", camera.full_render_px, FRAME_PX)
    }

    fn lighting(&self, lighting: &Lighting) -> Result<()> {
        let [x, y, z] = lighting.to_light;
        if !(x.is_finite() && y.is_finite() && z.is_finite() && x.hypot(y).hypot(z) > 0.0) {
            return self.refuse(
                "lighting.to_light",
                format!("{:?} is not a direction", lighting.to_light),
            );
        }
        self.non_negative("lighting.ambient", lighting.ambient)?;
        self.non_negative("lighting.diffuse", lighting.diffuse)?;
        self.non_negative("lighting.headlight", lighting.headlight)
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn load(text: &str) -> Result<EnvConfig> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("variant.toml");
        std::fs::write(&path, text).unwrap();
        EnvConfig::load(&path)
    }

    #[test]
    fn a_variant_file_changes_only_the_fields_it_names() {
        let config =
            load("[reacher]\nbase_m = [0.035, -0.025]\narm_rgb = [0.3, 0.6, 0.8]\n").unwrap();
        let want = ReacherConfig {
            base_m: [0.035, -0.025],
            arm_rgb: [0.3, 0.6, 0.8],
            ..ReacherConfig::default()
        };
        assert_eq!(config, EnvConfig::Reacher(want));
        assert_eq!(config.kind(), EnvKind::Reacher);
        assert!(!config.is_default());
        // A nested table is partial too.
        let camera = load("[point-mass.camera]\nheight_m = 0.8\n").unwrap();
        let EnvConfig::PointMass(pm) = &camera else {
            panic!("{camera:?}")
        };
        assert_eq!(pm.camera.height_m, 0.8);
        assert_eq!(pm.camera.fovy_deg, 45.0);
        let fetch = load("[fetch.camera]\nazimuth_deg = 140.0\n[fetch.lighting]\nambient = 0.5\n[fetch.ik]\nmax_iterations = 50\n").unwrap();
        let EnvConfig::Fetch(fetch) = &fetch else {
            panic!("{fetch:?}")
        };
        let reach = FetchConfig::default();
        assert_eq!(fetch.camera.azimuth_deg, 140.0);
        assert_eq!(fetch.camera.lookat_m, reach.camera.lookat_m);
        assert_eq!(fetch.lighting.ambient, 0.5);
        assert_eq!(fetch.lighting.to_light, reach.lighting.to_light);
        assert_eq!(fetch.ik.max_iterations, 50);
        assert_eq!(
            fetch.ik.orientation_weight_m_per_rad,
            reach.ik.orientation_weight_m_per_rad
        );
        assert!(load("[fetch]\n").unwrap().is_default());
        for kind in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
            assert!(EnvConfig::from(kind).is_default());
            assert!(EnvConfig::from(kind).validate().is_ok(), "{kind}");
        }
    }

    #[test]
    fn a_wrong_variant_file_is_refused_in_one_line_naming_it() {
        for (text, wanted) in [
            ("[reacher]\nbase = [0.0, 0.0]\n", "base"),
            ("[robot]\n", "robot"),
            ("[reacher]\n[fetch]\n", "variant.toml"),
            ("[reacher]\nbase_m = [0.2, 0.0]\n", "reacher.base_m"),
            ("[point-mass]\nmass_kg = -1.0\n", "point-mass.mass_kg"),
            ("[point-mass.camera]\nheight = 0.8\n", "height"),
            ("[fetch.camera]\ndistanse_m = 1.0\n", "distanse_m"),
            ("[fetch.lighting]\nambient_light = 0.1\n", "ambient_light"),
            (
                "[fetch.ik]\norientation_weight = 1.0\n",
                "orientation_weight",
            ),
            (
                "[fetch]\nworkspace_hi_m = [1.0, 0.9, 0.7]\n",
                "fetch.workspace_lo_m",
            ),
            (
                "[fetch.camera]\nfull_render_px = 0\n",
                "fetch.camera.full_render_px",
            ),
            ("[fetch.camera]\nfovy_deg = 0.0\n", "fetch.camera.fovy_deg"),
            (
                "[fetch.camera]\ndistance_m = 0.0\n",
                "fetch.camera.distance_m",
            ),
            ("[fetch]\nsamples_per_axis = 0\n", "fetch.samples_per_axis"),
            (
                "[fetch.ik]\nmax_iterations = 0\n",
                "fetch.ik.max_iterations",
            ),
            (
                "[fetch.lighting]\nambient = -5.0\n",
                "fetch.lighting.ambient",
            ),
            (
                "[fetch.lighting]\nto_light = [0.0, 0.0, 0.0]\n",
                "fetch.lighting.to_light",
            ),
            ("[fetch]\nsky_rgb = [0.4, 0.8, 255.0]\n", "fetch.sky_rgb"),
            (
                "[point-mass.camera]\nfovy_deg = 180.0\n",
                "point-mass.camera.fovy_deg",
            ),
            ("[point-mass]\ndamping = -1.0\n", "point-mass.damping"),
            (
                "[reacher.camera]\nheight_m = -1.0\n",
                "reacher.camera.height_m",
            ),
            ("[reacher]\narm_rgb = [0.3, 1.5, 0.8]\n", "reacher.arm_rgb"),
            (
                "[reacher.soft_limits]\nsolimp = [0.9, 0.95, 0.001, 0.5, 0.5]\n",
                "reacher.soft_limits.solimp",
            ),
        ] {
            let message = load(text).unwrap_err().to_string();
            assert!(message.contains(wanted), "{text}: {message}");
            assert!(!message.trim().contains('\n'), "{message}");
        }
    }
}
