//! Point mass-2D: dm_control's `point_mass` (two slide joints, soft walls) seen from above.

use super::mujoco::{Dynamics2, Joint, SoftLimitModel, euler_step};
use super::render2d::{Canvas, Shape, TopDownCamera};
use super::{Env, EnvKind, Frame, State, clip_action, validate_state};
use crate::error::Result;

/// Physical and visual parameters of the point mass (defaults from dm_control).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PointMassConfig {
    /// Control period and MuJoCo timestep, seconds (one physics step per control step).
    pub control_dt_s: f64,
    /// Mass of the ball, kg.
    pub mass_kg: f64,
    /// Viscous damping of each slide joint, N s/m.
    pub damping: f64,
    /// Actuator gear: newtons per unit of control.
    pub gear: f64,
    /// Joint range of x and y, metres (symmetric: [-limit, +limit]).
    pub joint_limit_m: f64,
    /// MuJoCo soft-limit parameters of the walls.
    pub soft_limits: SoftLimitModel,
    /// Radius the ball is drawn with, metres (dm_control's 0.01 is 2 px wide; 0.04 is learnable).
    pub ball_radius_m: f64,
    /// Ball colour, RGB in [0, 1].
    pub ball_rgb: [f32; 3],
    /// The top-down camera.
    pub camera: TopDownCamera,
}

impl Default for PointMassConfig {
    fn default() -> Self {
        Self {
            control_dt_s: 0.02,
            mass_kg: 0.3,
            damping: 1.0,
            gear: 0.1,
            joint_limit_m: 0.29,
            soft_limits: SoftLimitModel::default(),
            ball_radius_m: 0.04,
            ball_rgb: [0.7, 0.5, 0.3],
            camera: TopDownCamera::default(),
        }
    }
}

/// The point-mass environment: state `q = (x, y)` in metres, action = force per axis.
#[derive(Debug, Clone)]
pub struct PointMass {
    config: PointMassConfig,
    joints: [Joint; 2],
    q: [f64; 2],
    qd: [f64; 2],
    canvas: Canvas,
}

impl PointMass {
    /// Builds the environment at the origin, at rest.
    pub fn new(config: PointMassConfig) -> Self {
        let joint = Joint {
            range: [-config.joint_limit_m, config.joint_limit_m],
            damping: config.damping,
            gear: config.gear,
        };
        let canvas = Canvas::new(config.camera);
        Self {
            joints: [joint; 2],
            q: [0.0; 2],
            qd: [0.0; 2],
            canvas,
            config,
        }
    }

    /// The configuration this environment was built from.
    pub fn config(&self) -> &PointMassConfig {
        &self.config
    }

    /// The shapes of the current state, for the renderer.
    fn shapes(&self) -> [Shape; 1] {
        [Shape::Disc {
            centre: self.q,
            radius: self.config.ball_radius_m,
            rgb: self.config.ball_rgb,
        }]
    }
}

impl Env for PointMass {
    fn kind(&self) -> EnvKind {
        EnvKind::PointMass
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
        validate_state("point-mass", state, 2)?;
        self.q = [state.q[0], state.q[1]];
        self.qd = [state.qd[0], state.qd[1]];
        Ok(())
    }
    fn config_ranges(&self) -> Vec<[f64; 2]> {
        self.joints.map(|j| j.range).to_vec()
    }
    fn step(&mut self, action: &[f64]) {
        // The two slide joints are orthogonal: M = m I, no bias forces. MuJoCo's dof_invweight0
        // is 1/m for each.
        let m = self.config.mass_kg;
        let dynamics = Dynamics2 {
            mass: [[m, 0.0], [0.0, m]],
            bias: [0.0; 2],
        };
        euler_step(
            &mut self.q,
            &mut self.qd,
            clip_action(action),
            &self.joints,
            &dynamics,
            [1.0 / m; 2],
            &self.config.soft_limits,
            self.config.control_dt_s,
        );
    }
    fn render(&mut self, frame: &mut Frame) {
        let shapes = self.shapes();
        self.canvas.render(&shapes, frame);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    /// MuJoCo's reference: u = (1, 0) from rest at the origin, MuJoCo 3.17 (also reproduced with
    /// MuJoCo 4.0 by tools/mujoco_reference.py).
    #[test]
    fn step_response_matches_mujoco() {
        let mut env = PointMass::new(PointMassConfig::default());
        let expected = [
            (1, 0.000125000, 0.006250000),
            (5, 0.001725893, 0.027580357),
            (10, 0.005733814, 0.047553952),
            (25, 0.025975898, 0.080080341),
            (50, 0.071190379, 0.096032072),
        ];
        let mut k = 0;
        for (steps, x, v) in expected {
            while k < steps {
                env.step(&[1.0, 0.0]);
                k += 1;
            }
            let s = env.state();
            assert!(
                close(s.q[0], x, 1e-9) && close(s.qd[0], v, 1e-9),
                "t={steps}: {s:?}"
            );
            assert_eq!(s.q[1], 0.0);
        }
    }

    /// Driven into the +x and -y walls, then released. Pinned from MuJoCo 4.0 by
    /// tools/mujoco_reference.py (the walls are soft: a slight overshoot, then pushed back).
    #[test]
    fn soft_walls_match_mujoco() {
        let mut env = PointMass::new(PointMassConfig::default());
        env.set_state(&State {
            q: vec![0.2, -0.1],
            qd: vec![0.0, 0.0],
        })
        .unwrap();
        let golden: [(usize, [f64; 2], [f64; 2]); 6] = [
            (
                60,
                [0.2906243064742257, -0.19062430647422587],
                [0.09791897841924736, -0.09791897841924736],
            ),
            (
                100,
                [0.2900591784487073, -0.27004723336587044],
                [-1.4207568295714762e-07, -0.09984255544709855],
            ),
            (
                150,
                [0.2900591697777782, -0.2900591733052503],
                [-2.0579631748729454e-13, 5.7798724607642515e-08],
            ),
            (
                151,
                [0.2900467135410576, -0.29004671620309497],
                [-0.0006228118360286623, 0.0006228551077665948],
            ),
            (
                160,
                [0.28996439485149367, -0.28996439179419087],
                [-0.00034841620414886626, 0.0003484404114195139],
            ),
            (
                200,
                [0.2898677780629947, -0.2898677682929478],
                [-2.6360242485326925e-05, 2.6362073942981816e-05],
            ),
        ];
        let mut k = 0;
        for (steps, q, qd) in golden {
            while k < steps {
                let u = if k < 150 { [1.0, -1.0] } else { [0.0, 0.0] };
                env.step(&u);
                k += 1;
            }
            let s = env.state();
            for i in 0..2 {
                assert!(close(s.q[i], q[i], 1e-9), "k={steps} q: {:?} vs {q:?}", s.q);
                assert!(
                    close(s.qd[i], qd[i], 1e-7),
                    "k={steps} qd: {:?} vs {qd:?}",
                    s.qd
                );
            }
        }
    }
}
