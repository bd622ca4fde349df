//! Fetch-3D: gym's FetchReach with the end effector driven by acceleration, the 7-DOF arm posed
//! by inverse kinematics and the scene ray cast in 3D.

use super::fetch_arm::{ARM_JOINTS, ArmPose, IkConfig, IkSolution, forward_kinematics};
use super::render3d::{Lighting, Object, OrbitCamera, Picked, RayCaster, Solid, Vec3};
use super::{Env, EnvKind, Frame, State, clip_action, validate_state};
use crate::error::{Error, Result};

/// Dynamics, scene and rendering parameters (defaults from FetchReach).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FetchConfig {
    /// Control period, seconds.
    pub control_dt_s: f64,
    /// End-effector acceleration at full control, m/s^2. 0.5 makes a 0.3 m workspace crossing
    /// take 1.1 s from rest at full throttle and 1.55 s rest to rest (accelerate, then brake),
    /// inside 1-2 s; top speeds stay near 0.4 m/s, 1.6 cm (~1 px) per step.
    pub max_accel_m_s2: f64,
    /// The workspace box (FetchReach's goal box), lower and upper corners, metres.
    pub workspace_lo_m: [f64; 3],
    pub workspace_hi_m: [f64; 3],
    /// End-effector position of a freshly built environment (FetchReach's initial gripper).
    pub initial_grip_m: [f64; 3],
    /// Inverse kinematics weights.
    pub ik: IkConfig,
    /// FetchReach's camera.
    pub camera: OrbitCamera,
    pub lighting: Lighting,
    /// Rays per pixel along each axis (2: 4 rays per pixel, anti-aliased).
    pub samples_per_axis: usize,
    /// Colours, RGB in [0, 1].
    pub floor_rgb: [f32; 3],
    pub table_rgb: [f32; 3],
    pub sky_rgb: [f32; 3],
    pub robot_rgb: [f32; 3],
    pub arm_white_rgb: [f32; 3],
    pub arm_blue_rgb: [f32; 3],
    pub gripper_rgb: [f32; 3],
}

impl Default for FetchConfig {
    fn default() -> Self {
        Self {
            control_dt_s: 0.04,
            max_accel_m_s2: 0.5,
            workspace_lo_m: [1.19, 0.60, 0.385],
            workspace_hi_m: [1.49, 0.90, 0.685],
            initial_grip_m: [1.3418, 0.7491, 0.5347],
            ik: IkConfig::default(),
            camera: OrbitCamera::default(),
            lighting: Lighting::default(),
            samples_per_axis: 2,
            floor_rgb: [0.2, 0.2, 0.2],
            table_rgb: [0.93, 0.93, 0.93],
            sky_rgb: [0.44, 0.85, 0.56],
            robot_rgb: [0.78, 0.78, 0.8],
            arm_white_rgb: [0.9, 0.9, 0.9],
            arm_blue_rgb: [0.1, 0.3, 0.65],
            gripper_rgb: [0.25, 0.25, 0.28],
        }
    }
}

/// Capsule radius of the link from joint i to joint i+1 (the last: the wrist roll link), m.
const LINK_RADII_M: [f64; ARM_JOINTS] = [0.065, 0.06, 0.055, 0.055, 0.05, 0.045, 0.045];
/// Length of the wrist roll link's capsule along its x axis, m (the palm takes over there).
const WRIST_LINK_M: f64 = 0.06;
/// Gripper palm: centre along the gripper x axis and half-extents in the gripper frame, m.
const PALM_CENTRE_X_M: f64 = -0.055;
const PALM_HALF_M: [f64; 3] = [0.05, 0.06, 0.03];
/// Fingers: centre along x, offset either side along y, and half-extents, m. The grip site
/// (x = 0.02) sits in the gap between them.
const FINGER_CENTRE_X_M: f64 = 0.02;
const FINGER_OFFSET_Y_M: f64 = 0.03;
const FINGER_HALF_M: [f64; 3] = [0.025, 0.008, 0.015];

/// Labels of the scene's objects (what [`Fetch::pick`] reports).
pub const GRIPPER_LABEL: &str = "gripper";
pub const ARM_LABEL: &str = "arm";
pub const TABLE_LABEL: &str = "table";

/// Tolerance for states set slightly outside the workspace box (f32 round-off of stored
/// states), metres; they are clamped onto the box.
const BOX_TOLERANCE_M: f64 = 1e-6;

/// The Fetch-3D environment: `q` = end-effector position p (m), `qd` = its velocity (m/s),
/// action = end-effector acceleration as a fraction of `max_accel_m_s2` per axis.
#[derive(Debug, Clone)]
pub struct Fetch {
    config: FetchConfig,
    p: [f64; 3],
    v: [f64; 3],
    /// The arm pose for `p` (a function of `p` alone, see `fetch_arm`).
    arm: IkSolution,
    caster: RayCaster,
}

impl Fetch {
    /// Builds the environment with the gripper at `initial_grip_m`, at rest, and casts the
    /// static scene.
    pub fn new(config: FetchConfig) -> Self {
        let caster = RayCaster::new(
            &config.camera,
            config.lighting,
            static_scene(&config),
            config.sky_rgb,
            config.samples_per_axis,
        );
        let p = config.initial_grip_m;
        let arm = config.ik.solve(Vec3::from_array(p));
        Self {
            p,
            v: [0.0; 3],
            arm,
            caster,
            config,
        }
    }

    /// The configuration this environment was built from.
    pub fn config(&self) -> &FetchConfig {
        &self.config
    }

    /// The arm's joint angles for the current end-effector position, rad (shoulder pan, shoulder
    /// lift, upper-arm roll, elbow flex, forearm roll, wrist flex, wrist roll).
    pub fn joint_angles(&self) -> [f64; ARM_JOINTS] {
        self.arm.q
    }

    /// Distance between the rendered grip site and the state's end-effector position, m.
    pub fn ik_residual_m(&self) -> f64 {
        self.arm.position_error_m
    }

    /// The full IK result for the current position (angles, position and orientation errors).
    pub fn ik_solution(&self) -> &IkSolution {
        &self.arm
    }

    /// What the ray through continuous pixel coordinates (x, y) of the observation hits first:
    /// its label (`gripper`, `arm`, `table`, `floor`, `robot`) and the world point; `None` for
    /// sky.
    pub fn pick(&self, x: f64, y: f64) -> Option<Picked> {
        self.caster.pick(&self.arm_objects(), x, y)
    }

    fn set_position(&mut self, p: [f64; 3]) {
        self.p = p;
        self.arm = self.config.ik.solve(Vec3::from_array(p));
    }

    /// The moving solids: arm link capsules, gripper palm and fingers.
    fn arm_objects(&self) -> [Object; ARM_JOINTS + 3] {
        let pose: ArmPose = forward_kinematics(&self.arm.q);
        let c = &self.config;
        let link = |i: usize| {
            let a = pose.joints[i].origin;
            let b = match pose.joints.get(i + 1) {
                Some(next) => next.origin,
                None => a + pose.joints[i].rotation.cols[0] * WRIST_LINK_M,
            };
            Object {
                solid: Solid::Capsule {
                    a,
                    b,
                    radius: LINK_RADII_M[i],
                },
                // Alternating like the Fetch: white pan, blue lift, white roll, ...
                rgb: if i % 2 == 1 {
                    c.arm_blue_rgb
                } else {
                    c.arm_white_rgb
                },
                label: ARM_LABEL,
            }
        };
        let g = pose.gripper;
        let gripper_box = |x: f64, y: f64, half: [f64; 3]| Object {
            solid: Solid::Cuboid {
                centre: g.origin + g.rotation.apply(Vec3::new(x, y, 0.0)),
                axes: g.rotation,
                half: Vec3::from_array(half),
            },
            rgb: c.gripper_rgb,
            label: GRIPPER_LABEL,
        };
        [
            link(0),
            link(1),
            link(2),
            link(3),
            link(4),
            link(5),
            link(6),
            gripper_box(PALM_CENTRE_X_M, 0.0, PALM_HALF_M),
            gripper_box(FINGER_CENTRE_X_M, FINGER_OFFSET_Y_M, FINGER_HALF_M),
            gripper_box(FINGER_CENTRE_X_M, -FINGER_OFFSET_Y_M, FINGER_HALF_M),
        ]
    }
}

/// Floor, table and the fixed robot base, torso and head (FetchReach's geometry: `floor0` is a
/// 1.7 x 1.4 m plane centred at (0.8, 0.75); the base sits under the pan link, the torso behind
/// it up to z = 1.03 m).
fn static_scene(c: &FetchConfig) -> Vec<Object> {
    let aabb = |centre: [f64; 3], half: [f64; 3], rgb: [f32; 3], label: &'static str| Object {
        solid: Solid::aabb(Vec3::from_array(centre), Vec3::from_array(half)),
        rgb,
        label,
    };
    vec![
        aabb(
            [0.8, 0.75, -0.005],
            [0.85, 0.7, 0.005],
            c.floor_rgb,
            "floor",
        ),
        aabb(
            [1.3, 0.75, 0.2],
            [0.25, 0.35, 0.2],
            c.table_rgb,
            TABLE_LABEL,
        ),
        Object {
            solid: Solid::Cylinder {
                base: Vec3::new(0.692, 0.744, 0.0),
                height: 0.37,
                radius: 0.27,
            },
            rgb: c.robot_rgb,
            label: "robot",
        },
        aabb(
            [0.60, 0.744, 0.70],
            [0.10, 0.14, 0.33],
            c.robot_rgb,
            "robot",
        ),
        aabb(
            [0.66, 0.744, 1.10],
            [0.11, 0.14, 0.07],
            c.robot_rgb,
            "robot",
        ),
    ]
}

impl Env for Fetch {
    fn kind(&self) -> EnvKind {
        EnvKind::Fetch
    }
    fn control_dt_s(&self) -> f64 {
        self.config.control_dt_s
    }
    fn action_dim(&self) -> usize {
        3
    }
    fn config_dim(&self) -> usize {
        3
    }
    fn state(&self) -> State {
        State {
            q: self.p.to_vec(),
            qd: self.v.to_vec(),
        }
    }
    /// Teleports the end effector; positions within 1e-6 m outside the workspace box are
    /// clamped onto it, further out is an error. The arm pose is solved afresh (deterministic).
    fn set_state(&mut self, state: &State) -> Result<()> {
        validate_state("fetch", state, 3)?;
        let (lo, hi) = (self.config.workspace_lo_m, self.config.workspace_hi_m);
        let mut p = [0.0; 3];
        for i in 0..3 {
            let x = state.q[i];
            if x < lo[i] - BOX_TOLERANCE_M || x > hi[i] + BOX_TOLERANCE_M {
                return Err(Error::InvalidState {
                    env: "fetch",
                    message: format!(
                        "end-effector position {:?} m is outside the workspace box {lo:?} - {hi:?}",
                        state.q
                    ),
                });
            }
            p[i] = x.clamp(lo[i], hi[i]);
        }
        self.v = [state.qd[0], state.qd[1], state.qd[2]];
        self.set_position(p);
        Ok(())
    }
    fn config_ranges(&self) -> Vec<[f64; 2]> {
        (0..3)
            .map(|i| [self.config.workspace_lo_m[i], self.config.workspace_hi_m[i]])
            .collect()
    }
    /// `v' = v + dt a_max a`, `p' = p + dt v'`; at a wall p stops on the wall and the velocity
    /// component into it becomes 0.
    fn step(&mut self, action: &[f64]) {
        let a: [f64; 3] = clip_action(action);
        let c = &self.config;
        let dt = c.control_dt_s;
        let mut p = self.p;
        for i in 0..3 {
            let mut v = self.v[i] + dt * c.max_accel_m_s2 * a[i];
            let mut x = p[i] + dt * v;
            if x <= c.workspace_lo_m[i] {
                x = c.workspace_lo_m[i];
                v = v.max(0.0);
            } else if x >= c.workspace_hi_m[i] {
                x = c.workspace_hi_m[i];
                v = v.min(0.0);
            }
            p[i] = x;
            self.v[i] = v;
        }
        self.set_position(p);
    }
    fn render(&mut self, frame: &mut Frame) {
        let objects = self.arm_objects();
        self.caster.render(&objects, frame);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(p: [f64; 3], v: [f64; 3]) -> State {
        State {
            q: p.to_vec(),
            qd: v.to_vec(),
        }
    }

    #[test]
    fn double_integrator_with_walls() {
        let mut env = Fetch::new(FetchConfig::default());
        env.set_state(&at([1.3, 0.75, 0.5], [0.0; 3])).unwrap();
        env.step(&[1.0, -0.5, 0.0]);
        let s = env.state();
        // v' = 0.04 * 0.5 * a, p' = p + 0.04 v'.
        assert!((s.qd[0] - 0.02).abs() < 1e-15 && (s.qd[1] + 0.01).abs() < 1e-15);
        assert!((s.q[0] - 1.3008).abs() < 1e-12 && (s.q[1] - 0.7496).abs() < 1e-12);
        assert_eq!((s.q[2], s.qd[2]), (0.5, 0.0));
        // Driven into the +x wall: it stops on the wall with zero velocity into it, while the
        // other axes keep moving.
        env.set_state(&at([1.48, 0.75, 0.5], [0.3, 0.1, 0.0]))
            .unwrap();
        env.step(&[1.0, 0.0, 0.0]);
        let s = env.state();
        assert_eq!((s.q[0], s.qd[0]), (1.49, 0.0));
        assert!((s.q[1] - 0.754).abs() < 1e-12 && s.qd[1] == 0.1);
        // Pulled back out, it leaves the wall.
        env.step(&[-1.0, 0.0, 0.0]);
        assert!(env.state().q[0] < 1.49 && env.state().qd[0] < 0.0);
        // The arm follows: the IK residual stays tiny.
        assert!(env.ik_residual_m() < 1e-3);
    }

    #[test]
    fn full_throttle_crosses_the_workspace_in_one_to_two_seconds() {
        let mut env = Fetch::new(FetchConfig::default());
        env.set_state(&at([1.19, 0.75, 0.5], [0.0; 3])).unwrap();
        let mut steps = 0;
        while env.state().q[0] < 1.49 {
            env.step(&[1.0, 0.0, 0.0]);
            steps += 1;
        }
        let seconds = steps as f64 * env.control_dt_s();
        assert!((1.0..=2.0).contains(&seconds), "{seconds} s");
    }

    #[test]
    fn set_state_validates_and_teleports_deterministically() {
        let mut env = Fetch::new(FetchConfig::default());
        for bad in [
            State {
                q: vec![1.3, 0.75],
                qd: vec![0.0; 3],
            },
            at([f64::NAN, 0.75, 0.5], [0.0; 3]),
            at([1.3, 0.75, 0.5], [0.0, f64::INFINITY, 0.0]),
            at([1.0, 0.75, 0.5], [0.0; 3]),
        ] {
            let err = env.set_state(&bad).unwrap_err().to_string();
            assert!(err.contains("fetch"), "{err}");
        }
        // Within the tolerance: clamped onto the wall.
        env.set_state(&at([1.49 + 5e-7, 0.6, 0.385], [0.0; 3]))
            .unwrap();
        assert_eq!(env.state().q, vec![1.49, 0.6, 0.385]);
        // The arm pose depends on the position only, not on how the arm got there.
        let target = at([1.25, 0.82, 0.45], [0.0; 3]);
        env.set_state(&target).unwrap();
        let (q1, mut f1) = (env.joint_angles(), [0u8; crate::envs::FRAME_BYTES]);
        env.render(&mut f1);
        let mut other = Fetch::new(FetchConfig::default());
        other.set_state(&at([1.45, 0.62, 0.65], [0.0; 3])).unwrap();
        for _ in 0..30 {
            other.step(&[0.3, -0.2, 0.1]);
        }
        other.set_state(&target).unwrap();
        let mut f2 = [0u8; crate::envs::FRAME_BYTES];
        other.render(&mut f2);
        assert_eq!(q1, other.joint_angles());
        assert!(f1 == f2);
    }

    #[test]
    fn reset_pose_is_fetch_reach() {
        let env = Fetch::new(FetchConfig::default());
        let q = env.joint_angles();
        for (a, b) in q.iter().zip(super::super::fetch_arm::RESET_Q) {
            assert!((a - b).abs() < 0.05, "{q:?}");
        }
        let down = forward_kinematics(&q).gripper.rotation.cols[0];
        assert!(down.z < -0.999, "{down:?}");
    }
}
