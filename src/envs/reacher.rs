//! Reacher-2D: dm_control's two-link `reacher` with NewtonianVAE's joint ranges, seen from above.

use super::mujoco::{Dynamics2, Joint, Mat2, SoftLimitModel, euler_step};
use super::render2d::{Canvas, Shape, TopDownCamera};
use super::{Env, EnvKind, FieldCheck, Frame, State, clip_action, validate_state};
use crate::error::{Error, Result};

/// Physical and visual parameters of the reacher (defaults from dm_control). A TOML table of
/// some of the fields changes only those (`procl collect --env-config`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReacherConfig {
    /// Control period and MuJoCo timestep, seconds.
    pub control_dt_s: f64,
    /// Upper arm: length (shoulder to wrist), m.
    pub link1_length_m: f64,
    /// Upper arm: mass (kg), COM distance from the shoulder (m), inertia about its COM (kg m^2).
    pub link1_mass_kg: f64,
    pub link1_com_m: f64,
    pub link1_inertia: f64,
    /// Hand + finger: mass (kg), COM distance from the wrist (m), inertia about its COM (kg m^2).
    pub link2_mass_kg: f64,
    pub link2_com_m: f64,
    pub link2_inertia: f64,
    /// Fingertip distance from the wrist, m.
    pub fingertip_m: f64,
    /// Hand capsule length from the wrist (dm_control: 0.1 m; the finger sphere sits at 0.12 m).
    pub hand_length_m: f64,
    /// Joint damping, N m s/rad.
    pub damping: f64,
    /// Actuator gear, N m per unit of control.
    pub gear: f64,
    /// Shoulder and wrist ranges, degrees (the wrist bends one way only).
    pub shoulder_range_deg: [f64; 2],
    pub wrist_range_deg: [f64; 2],
    /// MuJoCo soft-limit parameters of the joint limits.
    pub soft_limits: SoftLimitModel,
    /// Radius the capsules are drawn with, m (dm_control's 0.01 is 2 px wide at 64x64).
    pub link_radius_m: f64,
    /// Radius the fingertip is drawn with, m.
    pub fingertip_radius_m: f64,
    /// Arm and fingertip colours, RGB in [0, 1].
    pub arm_rgb: [f32; 3],
    pub fingertip_rgb: [f32; 3],
    /// Where the shoulder stands on the floor, m from the point under the camera (the image
    /// centre); the kinematics are relative to it, so distances between configurations do not
    /// depend on it.
    pub base_m: [f64; 2],
    /// The top-down camera.
    pub camera: TopDownCamera,
}

impl Default for ReacherConfig {
    fn default() -> Self {
        Self {
            control_dt_s: 0.02,
            link1_length_m: 0.12,
            link1_mass_kg: 0.04188790205,
            link1_com_m: 0.06,
            link1_inertia: 6.331356395e-5,
            link2_mass_kg: 0.03979350695,
            link2_com_m: 0.05736842105,
            link2_inertia: 5.770775011e-5,
            fingertip_m: 0.12,
            hand_length_m: 0.1,
            damping: 0.01,
            gear: 0.05,
            shoulder_range_deg: [-160.0, 160.0],
            wrist_range_deg: [0.0, 160.0],
            soft_limits: SoftLimitModel::default(),
            link_radius_m: 0.02,
            fingertip_radius_m: 0.025,
            arm_rgb: [0.7, 0.5, 0.3],
            fingertip_rgb: [0.7, 0.4, 0.2],
            base_m: [0.0, 0.0],
            camera: TopDownCamera::default(),
        }
    }
}

impl ReacherConfig {
    /// Refuses a configuration the simulator cannot run or the camera cannot see whole: a
    /// non-positive length, mass or period, an empty joint range, or an arm whose reach leaves
    /// the image.
    pub fn validate(&self) -> Result<()> {
        let fields = FieldCheck(EnvKind::Reacher);
        fields.non_negative("damping", self.damping)?;
        fields.soft_limits(&self.soft_limits)?;
        fields.colour("arm_rgb", self.arm_rgb)?;
        fields.colour("fingertip_rgb", self.fingertip_rgb)?;
        // Before the arm's reach is held against the camera's view.
        fields.top_down_camera(&self.camera)?;
        let positive = [
            ("control_dt_s", self.control_dt_s),
            ("link1_length_m", self.link1_length_m),
            ("link1_mass_kg", self.link1_mass_kg),
            ("link1_inertia", self.link1_inertia),
            ("link2_mass_kg", self.link2_mass_kg),
            ("link2_inertia", self.link2_inertia),
            ("fingertip_m", self.fingertip_m),
            ("hand_length_m", self.hand_length_m),
            ("gear", self.gear),
            ("link_radius_m", self.link_radius_m),
            ("fingertip_radius_m", self.fingertip_radius_m),
        ];
        for (field, value) in positive {
            fields.positive(field, value)?;
        }
        for (field, [lo, hi]) in [
            ("shoulder_range_deg", self.shoulder_range_deg),
            ("wrist_range_deg", self.wrist_range_deg),
        ] {
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(Error::config(
                    format!("reacher.{field}"),
                    format!("[{lo}, {hi}] is not a range (lower < upper)"),
                ));
            }
        }
        if !self.base_m.iter().all(|x| x.is_finite()) {
            return Err(Error::config(
                "reacher.base_m",
                format!("{:?} must be finite", self.base_m),
            ));
        }
        let reach = self.base_m[0].hypot(self.base_m[1])
            + self.link1_length_m
            + self.fingertip_m.max(self.hand_length_m)
            + self.fingertip_radius_m.max(self.link_radius_m);
        let half = self.camera.half_width_m();
        if reach > half {
            return Err(Error::config(
                "reacher.base_m",
                format!(
                    "the arm reaches {reach:.3} m from the image centre, past the camera's {half:.3} m: shorten the links or move the base in"
                ),
            ));
        }
        Ok(())
    }
}

/// The reacher environment: `q = (shoulder, wrist)` in radians, action = joint torques.
#[derive(Debug, Clone)]
pub struct Reacher {
    config: ReacherConfig,
    joints: [Joint; 2],
    invweight0: [f64; 2],
    q: [f64; 2],
    qd: [f64; 2],
    canvas: Canvas,
}

impl Reacher {
    /// Builds the environment at q = 0, at rest ([`ReacherConfig::validate`] says whether the
    /// configuration is usable).
    pub fn new(config: ReacherConfig) -> Self {
        let joint = |range_deg: [f64; 2]| Joint {
            range: range_deg.map(f64::to_radians),
            damping: config.damping,
            gear: config.gear,
        };
        let joints = [
            joint(config.shoulder_range_deg),
            joint(config.wrist_range_deg),
        ];
        let canvas = Canvas::new(config.camera);
        let mut env = Self {
            joints,
            invweight0: [0.0; 2],
            q: [0.0; 2],
            qd: [0.0; 2],
            canvas,
            config,
        };
        // MuJoCo's dof_invweight0: the diagonal of M^-1 at the reference configuration q = 0.
        let m = env.mass_matrix([0.0; 2]);
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        env.invweight0 = [m[1][1] / det, m[0][0] / det];
        env
    }

    /// The configuration this environment was built from.
    pub fn config(&self) -> &ReacherConfig {
        &self.config
    }

    /// Joint-space mass matrix of the planar two-link arm at configuration `q`.
    pub fn mass_matrix(&self, q: [f64; 2]) -> Mat2 {
        let c = &self.config;
        let (l1, m2, c2) = (c.link1_length_m, c.link2_mass_kg, c.link2_com_m);
        let link2_own = c.link2_inertia + m2 * c2 * c2;
        let coupling = m2 * l1 * c2 * q[1].cos();
        let m11 = c.link1_inertia
            + c.link1_mass_kg * c.link1_com_m.powi(2)
            + link2_own
            + m2 * l1 * l1
            + 2.0 * coupling;
        let m12 = link2_own + coupling;
        [[m11, m12], [m12, link2_own]]
    }

    /// Coriolis and centrifugal forces `c(q, qd)` of the arm.
    fn bias(&self, q: [f64; 2], qd: [f64; 2]) -> [f64; 2] {
        let c = &self.config;
        let h = c.link2_mass_kg * c.link1_length_m * c.link2_com_m * q[1].sin();
        [
            -h * (2.0 * qd[0] * qd[1] + qd[1] * qd[1]),
            h * qd[0] * qd[0],
        ]
    }

    /// Wrist and fingertip positions (m) relative to the shoulder for configuration `q`.
    pub fn forward_kinematics(&self, q: [f64; 2]) -> ([f64; 2], [f64; 2]) {
        let c = &self.config;
        let wrist = [c.link1_length_m * q[0].cos(), c.link1_length_m * q[0].sin()];
        let a = q[0] + q[1];
        let tip = [
            wrist[0] + c.fingertip_m * a.cos(),
            wrist[1] + c.fingertip_m * a.sin(),
        ];
        (wrist, tip)
    }

    fn shapes(&self) -> [Shape; 3] {
        let c = &self.config;
        let on_floor = |[x, y]: [f64; 2]| [x + c.base_m[0], y + c.base_m[1]];
        let (wrist, tip) = self.forward_kinematics(self.q);
        let a = self.q[0] + self.q[1];
        let hand_end = on_floor([
            wrist[0] + c.hand_length_m * a.cos(),
            wrist[1] + c.hand_length_m * a.sin(),
        ]);
        let (wrist, tip) = (on_floor(wrist), on_floor(tip));
        [
            Shape::Capsule {
                from: c.base_m,
                to: wrist,
                radius: c.link_radius_m,
                rgb: c.arm_rgb,
            },
            Shape::Capsule {
                from: wrist,
                to: hand_end,
                radius: c.link_radius_m,
                rgb: c.arm_rgb,
            },
            Shape::Disc {
                centre: tip,
                radius: c.fingertip_radius_m,
                rgb: c.fingertip_rgb,
            },
        ]
    }
}

impl Env for Reacher {
    fn kind(&self) -> EnvKind {
        EnvKind::Reacher
    }
    fn control_dt_s(&self) -> f64 {
        self.config.control_dt_s
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn config_dim(&self) -> usize {
        2
    }
    fn state(&self) -> State {
        State {
            q: self.q.to_vec(),
            qd: self.qd.to_vec(),
        }
    }
    fn set_state(&mut self, state: &State) -> Result<()> {
        validate_state("reacher", state, 2)?;
        self.q = [state.q[0], state.q[1]];
        self.qd = [state.qd[0], state.qd[1]];
        Ok(())
    }
    fn config_ranges(&self) -> Vec<[f64; 2]> {
        self.joints.map(|j| j.range).to_vec()
    }
    fn step(&mut self, action: &[f64]) {
        let dynamics = Dynamics2 {
            mass: self.mass_matrix(self.q),
            bias: self.bias(self.q, self.qd),
        };
        euler_step(
            &mut self.q,
            &mut self.qd,
            clip_action(action),
            &self.joints,
            &dynamics,
            self.invweight0,
            &self.config.soft_limits,
            self.config.control_dt_s,
        );
    }
    fn render(&mut self, frame: &mut Frame) {
        let shapes = self.shapes();
        self.canvas.render(&shapes, frame);
    }
    fn fingertip_distance_m(&self, a: &[f64], b: &[f64]) -> Option<f64> {
        let (_, ta) = self.forward_kinematics([a[0], a[1]]);
        let (_, tb) = self.forward_kinematics([b[0], b[1]]);
        Some(((ta[0] - tb[0]).powi(2) + (ta[1] - tb[1]).powi(2)).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The centre of the pure-red pixels of a frame, (column, row).
    fn red_centroid(frame: &Frame) -> (f64, f64) {
        let (mut sum, mut n) = ((0.0, 0.0), 0.0);
        for (k, px) in frame.chunks(3).enumerate() {
            if px[0] > 200 && px[1] < 40 && px[2] < 40 {
                sum.0 += (k % crate::envs::FRAME_PX) as f64;
                sum.1 += (k / crate::envs::FRAME_PX) as f64;
                n += 1.0;
            }
        }
        assert!(n > 20.0, "{n} red pixels");
        (sum.0 / n, sum.1 / n)
    }

    #[test]
    fn moving_the_base_moves_the_drawn_arm_and_not_its_kinematics() {
        let red = ReacherConfig {
            arm_rgb: [1.0, 0.0, 0.0],
            fingertip_rgb: [1.0, 0.0, 0.0],
            ..ReacherConfig::default()
        };
        let px = red.camera.px_per_m();
        // 3 px right and 2 px up on the floor: 2 rows towards the top of the image.
        let moved = ReacherConfig {
            base_m: [3.0 / px, 2.0 / px],
            ..red.clone()
        };
        let state = State {
            q: vec![0.7, 1.1],
            qd: vec![0.0, 0.0],
        };
        let mut frames = [[0u8; crate::envs::FRAME_BYTES]; 2];
        for (config, frame) in [red, moved].into_iter().zip(frames.iter_mut()) {
            let mut env = Reacher::new(config);
            env.set_state(&state).unwrap();
            env.render(frame);
        }
        let (a, b) = (red_centroid(&frames[0]), red_centroid(&frames[1]));
        assert!((b.0 - a.0 - 3.0).abs() < 0.05, "{a:?} -> {b:?}");
        assert!((b.1 - a.1 + 2.0).abs() < 0.05, "{a:?} -> {b:?}");
        let env = Reacher::new(ReacherConfig {
            base_m: [0.03, 0.0],
            ..ReacherConfig::default()
        });
        let straight = Reacher::new(ReacherConfig::default());
        assert_eq!(
            env.fingertip_distance_m(&[0.0, 0.0], &[1.0, 0.5]),
            straight.fingertip_distance_m(&[0.0, 0.0], &[1.0, 0.5])
        );
    }

    #[test]
    fn an_arm_that_leaves_the_image_or_cannot_be_simulated_is_refused_by_field() {
        assert!(ReacherConfig::default().validate().is_ok());
        let field = |config: ReacherConfig| match config.validate() {
            Err(Error::InvalidConfig { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        // The default arm reaches 0.265 m of the camera's 0.311 m: 0.05 m off centre is too far.
        let off = ReacherConfig {
            base_m: [0.0, -0.05],
            ..ReacherConfig::default()
        };
        assert_eq!(field(off), "reacher.base_m");
        let in_view = ReacherConfig {
            base_m: [0.035, -0.025],
            ..ReacherConfig::default()
        };
        assert!(in_view.validate().is_ok());
        let massless = ReacherConfig {
            link2_mass_kg: 0.0,
            ..ReacherConfig::default()
        };
        assert_eq!(field(massless), "reacher.link2_mass_kg");
        let backwards = ReacherConfig {
            wrist_range_deg: [10.0, -10.0],
            ..ReacherConfig::default()
        };
        assert_eq!(field(backwards), "reacher.wrist_range_deg");
    }

    #[test]
    fn fingertip_distance_is_measured_between_the_fingertips_in_metres() {
        let env = Reacher::new(ReacherConfig::default());
        // Straight along +x the fingertip is at (0.24, 0); with the wrist at 90 degrees it is
        // at (0.12, 0.12): 0.12 sqrt(2) m apart.
        let (straight, bent) = ([0.0, 0.0], [0.0, std::f64::consts::FRAC_PI_2]);
        let d = env.fingertip_distance_m(&straight, &bent).unwrap();
        assert!((d - 0.12 * 2f64.sqrt()).abs() < 1e-12, "{d}");
        // Turning the shoulder by pi with the arm straight moves it by the arm's full span.
        let d = env.fingertip_distance_m(&straight, &[std::f64::consts::PI, 0.0]);
        assert!((d.unwrap() - 0.48).abs() < 1e-12);
        assert_eq!(env.fingertip_distance_m(&bent, &bent), Some(0.0));
    }

    /// MuJoCo's reference (MuJoCo 3.17; MuJoCo 4.0 agrees, tools/mujoco_reference.py).
    #[test]
    fn mass_matrix_at_zero_matches_mujoco() {
        let env = Reacher::new(ReacherConfig::default());
        let m = env.mass_matrix([0.0, 0.0]);
        let expected = [
            [0.001523703853, 0.0004626204622],
            [0.0004626204622, 0.0001886735828],
        ];
        for i in 0..2 {
            for j in 0..2 {
                assert!(
                    (m[i][j] - expected[i][j]).abs() < 1e-12,
                    "M[{i}][{j}] = {}",
                    m[i][j]
                );
            }
        }
        // MuJoCo's dof_invweight0 for this model.
        assert!((env.invweight0[0] - 2568.2114217653902).abs() < 1e-6);
        assert!((env.invweight0[1] - 20740.54873181604).abs() < 1e-5);
    }

    /// Coupled swing into both limits and out again, pinned from MuJoCo 4.0 by
    /// tools/mujoco_reference.py: controls (1,-1) x100, (-1,1) x100, (0.3,0.7) x100 from
    /// q = (0.5, 1.0) at rest.
    #[test]
    fn trajectory_through_limits_matches_mujoco() {
        let mut env = Reacher::new(ReacherConfig::default());
        env.set_state(&State {
            q: vec![0.5, 1.0],
            qd: vec![0.0, 0.0],
        })
        .unwrap();
        let golden: [(usize, [f64; 2], [f64; 2]); 8] = [
            (
                1,
                [0.5316264092778814, 0.921146625909706],
                [1.5813204638940692, -3.9426687045147024],
            ),
            (
                10,
                [1.137785439725971, -0.06617577807246613],
                [4.00467378840797, -5.3300296760586185],
            ),
            (
                50,
                [2.8054169825519777, -0.08792286951231514],
                [0.003857225254708824, -0.06047057147169413],
            ),
            (
                100,
                [2.802794522176885, -0.08294939499547374],
                [-1.585503404273739e-05, 8.97913521584025e-05],
            ),
            (
                150,
                [-1.9694953381433224, 2.872534301242241],
                [-4.9916153256748625, -0.007310345029524695],
            ),
            (
                200,
                [-2.8027997957763287, 2.875488958255151],
                [2.9412116696312434e-06, 1.7144237589890534e-07],
            ),
            (
                250,
                [-1.370450889324109, 2.8503066292558783],
                [1.4999999833501547, -2.620853258597355e-08],
            ),
            (
                300,
                [0.1295491100975877, 2.850306628906763],
                [1.4999999999844718, -1.0648297915038267e-10],
            ),
        ];
        let mut k = 0;
        for (steps, q, qd) in golden {
            while k < steps {
                let u = match k {
                    0..100 => [1.0, -1.0],
                    100..200 => [-1.0, 1.0],
                    _ => [0.3, 0.7],
                };
                env.step(&u);
                k += 1;
            }
            let s = env.state();
            for i in 0..2 {
                assert!(
                    (s.q[i] - q[i]).abs() < 1e-8,
                    "k={steps} q: {:?} vs {q:?}",
                    s.q
                );
                assert!(
                    (s.qd[i] - qd[i]).abs() < 1e-6,
                    "k={steps} qd: {:?} vs {qd:?}",
                    s.qd
                );
            }
        }
    }
}
