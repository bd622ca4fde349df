//! MuJoCo's Euler step with implicit joint damping and soft joint limits, for two-dof systems.
//!
//! Both 2D environments (point mass, reacher) are two-joint MuJoCo models. This module reproduces
//! what `mj_step` does for them, in closed form:
//!
//! 1. smooth acceleration `a0 = M^-1 (gear u - D qd - bias)` (explicit damping, as MuJoCo's
//!    `qacc_smooth`);
//! 2. joint-limit constraint forces from MuJoCo's soft-constraint model (solref/solimp): a limit
//!    is active when its distance `r` is negative; its reference acceleration is
//!    `aref = -b (J qd) - k imp(r) r` with `k = 1/(dmax^2 tc^2 zeta^2)`, `b = 2/(dmax tc)`,
//!    `tc = max(timeconst, 2 dt)` (MuJoCo's "refsafe"), and its regulariser
//!    `R = (1 - imp)/imp * invweight0`. The forces solve MuJoCo's convex constraint problem
//!    `min 1/2 |a - a0|_M^2 + sum_i 1/(2 R_i) min(0, J_i a - aref_i)^2` exactly, by
//!    enumerating active sets (at most two constraints, one per joint);
//! 3. Euler integration with implicit damping:
//!    `qd' = qd + dt (M + dt D)^-1 (gear u - D qd - bias + J^T f)`, `q' = q + dt qd'`.
//!
//! Checked against MuJoCo itself (tools/mujoco_reference.py) in the environments' tests.

/// A 2x2 matrix, row-major.
pub type Mat2 = [[f64; 2]; 2];

/// MuJoCo's soft-constraint parameters for joint limits: `solref = (timeconst, dampratio)` and
/// `solimp = (dmin, dmax, width, midpoint, power)`. Defaults are MuJoCo's (and dm_control's).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SoftLimitModel {
    /// solref[0]: time constant of the constraint's mass-spring-damper, seconds.
    pub timeconst_s: f64,
    /// solref[1]: damping ratio of that mass-spring-damper.
    pub dampratio: f64,
    /// solimp: (dmin, dmax, width in metres or radians, midpoint, power).
    pub solimp: [f64; 5],
}

impl Default for SoftLimitModel {
    fn default() -> Self {
        Self {
            timeconst_s: 0.02,
            dampratio: 1.0,
            solimp: [0.9, 0.95, 0.001, 0.5, 2.0],
        }
    }
}

/// MuJoCo's smallest value used in place of zero (mjMINVAL).
const MJ_MINVAL: f64 = 1e-15;

impl SoftLimitModel {
    /// Constraint impedance `imp(r)` in (0, 1): MuJoCo's sigmoid from dmin (r = 0) to dmax
    /// (|r| >= width), two power-law halves meeting at the midpoint.
    pub fn impedance(&self, distance: f64) -> f64 {
        let [dmin, dmax, width, midpoint, power] = self.solimp;
        if dmin == dmax || width <= MJ_MINVAL {
            return 0.5 * (dmin + dmax);
        }
        let x = (distance / width).abs();
        if x >= 1.0 {
            return dmax;
        }
        if x <= 0.0 {
            return dmin;
        }
        let y = if power == 1.0 {
            x
        } else if x <= midpoint {
            x.powf(power) / midpoint.powf(power - 1.0)
        } else {
            1.0 - (1.0 - x).powf(power) / (1.0 - midpoint).powf(power - 1.0)
        };
        dmin + y * (dmax - dmin)
    }

    /// Stiffness `k` and damping `b` of the reference acceleration, for physics step `dt`.
    pub fn stiffness_damping(&self, dt: f64) -> (f64, f64) {
        let dmax = self.solimp[1];
        // MuJoCo's "refsafe": a time constant below two steps would be unstable with Euler.
        let timeconst = self.timeconst_s.max(2.0 * dt);
        let k = 1.0 / (dmax * dmax * timeconst * timeconst * self.dampratio * self.dampratio);
        let b = 2.0 / (dmax * timeconst);
        (k, b)
    }
}

/// One joint of a two-dof model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Joint {
    /// Lower and upper limit (m for slide joints, rad for hinges).
    pub range: [f64; 2],
    /// Viscous damping coefficient (N s/m or N m s/rad).
    pub damping: f64,
    /// Actuator gear: force or torque per unit of control.
    pub gear: f64,
}

/// The configuration-dependent terms of a two-dof rigid-body model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dynamics2 {
    /// Joint-space mass matrix `M(q)`.
    pub mass: Mat2,
    /// Coriolis/centrifugal bias force `c(q, qd)` (MuJoCo's `qfrc_bias` without gravity).
    pub bias: [f64; 2],
}

fn inverse(m: &Mat2) -> Mat2 {
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    [
        [m[1][1] / det, -m[0][1] / det],
        [-m[1][0] / det, m[0][0] / det],
    ]
}

fn mul(m: &Mat2, v: [f64; 2]) -> [f64; 2] {
    [
        m[0][0] * v[0] + m[0][1] * v[1],
        m[1][0] * v[0] + m[1][1] * v[1],
    ]
}

/// An active joint limit: which joint, its Jacobian sign (+1 lower, -1 upper), distance, R, aref.
#[derive(Debug, Clone, Copy)]
struct ActiveLimit {
    joint: usize,
    sign: f64,
    regulariser: f64,
    aref: f64,
}

/// Generalised constraint force `J^T f` of the active joint limits, as MuJoCo computes it.
///
/// `invweight0` is MuJoCo's `dof_invweight0`: the diagonal of `M^-1` at the model's reference
/// configuration, which MuJoCo uses (instead of the current `M`) to scale the regulariser.
#[allow(clippy::too_many_arguments)]
fn limit_forces(
    q: [f64; 2],
    qd: [f64; 2],
    joints: &[Joint; 2],
    dynamics: &Dynamics2,
    smooth_acc: [f64; 2],
    invweight0: [f64; 2],
    limits: &SoftLimitModel,
    dt: f64,
) -> [f64; 2] {
    let (k, b) = limits.stiffness_damping(dt);
    let mut active: Vec<ActiveLimit> = Vec::with_capacity(2);
    for (i, joint) in joints.iter().enumerate() {
        // Distance to each side of the range (negative = violated); at most one side can be.
        for (sign, distance) in [(1.0, q[i] - joint.range[0]), (-1.0, joint.range[1] - q[i])] {
            if distance < 0.0 {
                let imp = limits.impedance(distance);
                let velocity = sign * qd[i];
                active.push(ActiveLimit {
                    joint: i,
                    sign,
                    regulariser: ((1.0 - imp) / imp * invweight0[i]).max(MJ_MINVAL),
                    aref: -b * velocity - k * imp * distance,
                });
            }
        }
    }
    if active.is_empty() {
        return [0.0; 2];
    }
    let m_inv = inverse(&dynamics.mass);
    // Constraint-space quantities: A = J M^-1 J^T, and J a0.
    let a = |i: &ActiveLimit, j: &ActiveLimit| i.sign * j.sign * m_inv[i.joint][j.joint];
    let j_a0 = |c: &ActiveLimit| c.sign * smooth_acc[c.joint];

    // The constraint problem is convex with a unique solution; with at most two constraints the
    // active set is found by trying each subset: forces must be >= 0 on the chosen set, and the
    // others must not be violated by the resulting acceleration.
    let n = active.len();
    for subset in (1..(1u32 << n)).rev() {
        let chosen: Vec<usize> = (0..n).filter(|&i| subset & (1 << i) != 0).collect();
        let forces: Vec<f64> = match chosen.as_slice() {
            [i] => {
                let c = &active[*i];
                vec![(c.aref - j_a0(c)) / (a(c, c) + c.regulariser)]
            }
            [i, j] => {
                let (ci, cj) = (&active[*i], &active[*j]);
                let system = [
                    [a(ci, ci) + ci.regulariser, a(ci, cj)],
                    [a(cj, ci), a(cj, cj) + cj.regulariser],
                ];
                let rhs = [ci.aref - j_a0(ci), cj.aref - j_a0(cj)];
                mul(&inverse(&system), rhs).to_vec()
            }
            _ => unreachable!("at most two joint limits"),
        };
        if forces.iter().any(|&f| f < 0.0) {
            continue;
        }
        let mut generalised = [0.0; 2];
        for (&c, &f) in chosen.iter().zip(&forces) {
            generalised[active[c].joint] += active[c].sign * f;
        }
        let acc = {
            let delta = mul(&m_inv, generalised);
            [smooth_acc[0] + delta[0], smooth_acc[1] + delta[1]]
        };
        let others_satisfied = (0..n)
            .filter(|i| !chosen.contains(i))
            .all(|i| active[i].sign * acc[active[i].joint] - active[i].aref >= 0.0);
        if others_satisfied {
            return generalised;
        }
    }
    [0.0; 2]
}

/// One `mj_step` of a two-dof model with MuJoCo's Euler integrator and implicit damping.
/// `control` must already be clipped to the actuator range.
#[allow(clippy::too_many_arguments)]
pub fn euler_step(
    q: &mut [f64; 2],
    qd: &mut [f64; 2],
    control: [f64; 2],
    joints: &[Joint; 2],
    dynamics: &Dynamics2,
    invweight0: [f64; 2],
    limits: &SoftLimitModel,
    dt: f64,
) {
    let smooth_force: [f64; 2] = std::array::from_fn(|i| {
        joints[i].gear * control[i] - joints[i].damping * qd[i] - dynamics.bias[i]
    });
    let smooth_acc = mul(&inverse(&dynamics.mass), smooth_force);
    let constraint = limit_forces(
        *q, *qd, joints, dynamics, smooth_acc, invweight0, limits, dt,
    );
    let mut damped = dynamics.mass;
    for i in 0..2 {
        damped[i][i] += dt * joints[i].damping;
    }
    let acc = mul(
        &inverse(&damped),
        [
            smooth_force[0] + constraint[0],
            smooth_force[1] + constraint[1],
        ],
    );
    for i in 0..2 {
        qd[i] += dt * acc[i];
        q[i] += dt * qd[i];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn impedance_matches_mujoco_sigmoid() {
        let model = SoftLimitModel::default();
        // r = 0 -> dmin; |r| >= width -> dmax; at the midpoint exactly halfway.
        assert_eq!(model.impedance(0.0), 0.9);
        assert_eq!(model.impedance(-0.002), 0.95);
        assert!((model.impedance(-0.0005) - 0.925).abs() < 1e-12);
        // Quadratic lower half: x = 0.25 -> y = 0.25^2 / 0.5 = 0.125.
        assert!((model.impedance(-0.00025) - (0.9 + 0.125 * 0.05)).abs() < 1e-12);
    }

    #[test]
    fn refsafe_clamps_time_constant_to_two_steps() {
        let model = SoftLimitModel::default();
        let (k, b) = model.stiffness_damping(0.02);
        // tc = max(0.02, 0.04) = 0.04; k = 1/(0.95^2 0.04^2), b = 2/(0.95 0.04).
        assert!((k - 1.0 / (0.9025 * 0.0016)).abs() < 1e-9);
        assert!((b - 2.0 / 0.038).abs() < 1e-12);
    }
}
