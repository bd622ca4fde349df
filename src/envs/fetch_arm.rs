//! The Fetch 7-DOF arm: forward kinematics of the chain FetchReach compiles and an
//! inverse kinematics that places the grip site at a point with the gripper pointing down.
//!
//! The IK is a Levenberg-Marquardt least-squares solve over the joint angles, always started from
//! the FetchReach reset pose, so the arm pose is a function of the end-effector position alone:
//! the same position renders the same pixels whatever the history (a goal image set by teleport
//! matches the frame reached by driving there). Continuity from step to step comes from the
//! objective being smooth and having one minimum near the reset pose over the workspace, which
//! the tests check, instead of from warm starts (which would let the redundant elbow drift with
//! the history).

use super::render3d::{Mat3, Vec3};

/// Number of arm joints.
pub const ARM_JOINTS: usize = 7;

/// One revolute joint of the chain: its frame sits at `offset_m` in the parent's frame (all
/// frames unrotated at q = 0) and turns about the coordinate axis `axis` (0 = x, 1 = y, 2 = z).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmJoint {
    pub name: &'static str,
    pub offset_m: [f64; 3],
    pub axis: usize,
    /// Joint range, rad; `None` for continuous roll joints.
    pub limits_rad: Option<[f64; 2]>,
}

/// FetchReach's kinematic table; the first offset is the shoulder pan link's world position.
pub const FETCH_ARM: [ArmJoint; ARM_JOINTS] = [
    ArmJoint {
        name: "shoulder_pan",
        offset_m: [0.7244, 0.7441, 0.7273],
        axis: 2,
        limits_rad: Some([-1.6056, 1.6056]),
    },
    ArmJoint {
        name: "shoulder_lift",
        offset_m: [0.117, 0.0, 0.06],
        axis: 1,
        limits_rad: Some([-1.221, 1.518]),
    },
    ArmJoint {
        name: "upperarm_roll",
        offset_m: [0.219, 0.0, 0.0],
        axis: 0,
        limits_rad: None,
    },
    ArmJoint {
        name: "elbow_flex",
        offset_m: [0.133, 0.0, 0.0],
        axis: 1,
        limits_rad: Some([-2.251, 2.251]),
    },
    ArmJoint {
        name: "forearm_roll",
        offset_m: [0.197, 0.0, 0.0],
        axis: 0,
        limits_rad: None,
    },
    ArmJoint {
        name: "wrist_flex",
        offset_m: [0.1245, 0.0, 0.0],
        axis: 1,
        limits_rad: Some([-2.16, 2.16]),
    },
    ArmJoint {
        name: "wrist_roll",
        offset_m: [0.1385, 0.0, 0.0],
        axis: 0,
        limits_rad: None,
    },
];

/// Gripper link origin along the wrist roll link's x axis, m.
pub const GRIPPER_OFFSET_M: f64 = 0.1664;
/// Grip site (the end-effector point p) along the gripper link's x axis, m.
pub const GRIP_SITE_OFFSET_M: f64 = 0.02;

/// The joint angles FetchReach holds after reset, rad.
pub const RESET_Q: [f64; ARM_JOINTS] = [0.0097, -0.8257, -0.0031, 1.4441, 0.0026, 0.953, 0.0059];

/// The gripper orientation FetchReach's mocap holds: a quarter turn about world y, so the
/// gripper's x axis points down (-z), its y axis along world y and its z axis along world x.
pub const GRIPPER_DOWN: Mat3 = Mat3 {
    cols: [
        Vec3::new(0.0, 0.0, -1.0),
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(1.0, 0.0, 0.0),
    ],
};

/// A link frame in the world: origin and orientation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkFrame {
    pub origin: Vec3,
    pub rotation: Mat3,
}

/// Every frame of the arm at one configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmPose {
    /// Joint frames after each joint's rotation (the joint sits at the origin).
    pub joints: [LinkFrame; ARM_JOINTS],
    /// The gripper link's frame.
    pub gripper: LinkFrame,
    /// The grip site (end-effector point), world metres.
    pub grip_site: Vec3,
}

impl ArmPose {
    /// World axis of joint `i`.
    fn joint_axis(&self, i: usize) -> Vec3 {
        self.joints[i].rotation.cols[FETCH_ARM[i].axis]
    }
}

/// Forward kinematics: the frames of the chain at joint angles `q`.
pub fn forward_kinematics(q: &[f64; ARM_JOINTS]) -> ArmPose {
    let mut origin = Vec3::ZERO;
    let mut rotation = Mat3::IDENTITY;
    let mut joints = [LinkFrame { origin, rotation }; ARM_JOINTS];
    for (i, joint) in FETCH_ARM.iter().enumerate() {
        origin = origin + rotation.apply(Vec3::from_array(joint.offset_m));
        rotation = rotation.compose(&Mat3::about_axis(joint.axis, q[i]));
        joints[i] = LinkFrame { origin, rotation };
    }
    let x = rotation.cols[0];
    let gripper = LinkFrame {
        origin: origin + x * GRIPPER_OFFSET_M,
        rotation,
    };
    ArmPose {
        joints,
        gripper,
        grip_site: gripper.origin + x * GRIP_SITE_OFFSET_M,
    }
}

/// Weights of the IK objective
/// `|p* - p(q)|^2 + w_o^2 |e_R(q)|^2 + sum_i w_i^2 (q_i - q_reset,i)^2`.
///
/// The gripper cannot point straight down everywhere in the workspace (near the robot and high
/// the shoulder lift hits its limit; far and high the arm is 2-3 cm short), so the orientation is
/// a soft term, weak against position: where it is infeasible the gripper tilts by up to ~12 deg
/// and the grip site still lands within 0.3 mm (measured over 300 random targets: 0.25 mm).
/// The posture term picks one arm pose out of the redundant ones. It is stiff on the two
/// elbow-side rolls (upper arm and forearm): with them free, targets near the robot and high
/// have two mirror-image solutions with the elbow swung left or right, and the pose jumps
/// between them (measured: 0.5 rad jumps for 3 mm moves).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IkConfig {
    /// `w_o`: metres of position error worth one radian of orientation error.
    pub orientation_weight_m_per_rad: f64,
    /// `w_i` of the pan, lift, elbow, wrist flex and wrist roll joints, m/rad.
    pub posture_weight_m_per_rad: f64,
    /// `w_i` of the upper-arm and forearm roll joints, m/rad.
    pub elbow_roll_weight_m_per_rad: f64,
    /// Levenberg-Marquardt iterations at most (the workspace needs at most ~35).
    pub max_iterations: usize,
}

impl Default for IkConfig {
    fn default() -> Self {
        Self {
            orientation_weight_m_per_rad: 0.02,
            posture_weight_m_per_rad: 1e-3,
            elbow_roll_weight_m_per_rad: 0.03,
            max_iterations: 100,
        }
    }
}

/// An IK result.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    /// Joint angles, rad, inside the joint limits.
    pub q: [f64; ARM_JOINTS],
    /// Distance from the grip site to the target, m.
    pub position_error_m: f64,
    /// Rotation angle between the gripper frame and [`GRIPPER_DOWN`], rad.
    pub orientation_error_rad: f64,
    pub iterations: usize,
}

/// Residuals of the IK objective and their Jacobians at one configuration.
struct Linearised {
    /// Position residual `p* - p(q)`, orientation residual (axis-angle-like), posture residual.
    position: Vec3,
    orientation: Vec3,
    cost: f64,
    /// d(p(q))/dq and d(orientation)/dq, one column per joint.
    j_position: [Vec3; ARM_JOINTS],
    j_orientation: [Vec3; ARM_JOINTS],
}

impl IkConfig {
    fn posture_weights(&self) -> [f64; ARM_JOINTS] {
        let (w, roll) = (
            self.posture_weight_m_per_rad,
            self.elbow_roll_weight_m_per_rad,
        );
        [w, w, roll, w, roll, w, w]
    }

    fn linearise(&self, q: &[f64; ARM_JOINTS], target: Vec3) -> Linearised {
        let pose = forward_kinematics(q);
        let position = target - pose.grip_site;
        // 0.5 sum_k r_k x r*_k: zero when aligned, the rotation vector for small errors, and
        // d/dq = -(joint axis) near alignment (so the Jacobian below is the joint axis).
        let r = pose.gripper.rotation.cols;
        let orientation = (r[0].cross(GRIPPER_DOWN.cols[0])
            + r[1].cross(GRIPPER_DOWN.cols[1])
            + r[2].cross(GRIPPER_DOWN.cols[2]))
            * 0.5;
        let w = self.posture_weights();
        let posture: f64 = (0..ARM_JOINTS)
            .map(|i| (w[i] * (q[i] - RESET_Q[i])).powi(2))
            .sum();
        let wo = self.orientation_weight_m_per_rad;
        let j_position = std::array::from_fn(|i| {
            pose.joint_axis(i)
                .cross(pose.grip_site - pose.joints[i].origin)
        });
        Linearised {
            position,
            orientation,
            cost: position.dot(position) + wo * wo * orientation.dot(orientation) + posture,
            j_position,
            j_orientation: std::array::from_fn(|i| pose.joint_axis(i)),
        }
    }

    /// Places the grip site at `target` (world metres), gripper pointing down as far as the arm
    /// allows, joint limits respected. Deterministic: always starts from [`RESET_Q`].
    pub fn solve(&self, target: Vec3) -> IkSolution {
        let w = self.posture_weights();
        let wo2 = self.orientation_weight_m_per_rad.powi(2);
        let mut q = RESET_Q;
        let mut lin = self.linearise(&q, target);
        let mut damping = 1e-6;
        let mut iterations = 0;
        while iterations < self.max_iterations {
            iterations += 1;
            // Gauss-Newton normal equations H dq = g of the stacked residuals.
            let mut h = [[0.0; ARM_JOINTS]; ARM_JOINTS];
            let mut g = [0.0; ARM_JOINTS];
            for (a, row) in h.iter_mut().enumerate() {
                for (b, hab) in row.iter_mut().enumerate() {
                    *hab = lin.j_position[a].dot(lin.j_position[b])
                        + wo2 * lin.j_orientation[a].dot(lin.j_orientation[b]);
                }
                row[a] += w[a] * w[a];
                g[a] = lin.j_position[a].dot(lin.position)
                    + wo2 * lin.j_orientation[a].dot(lin.orientation)
                    + w[a] * w[a] * (RESET_Q[a] - q[a]);
            }
            // Levenberg-Marquardt: raise the damping until the step lowers the cost.
            let accepted = loop {
                let dq = limited_step(&h, &g, damping, &q);
                let candidate = clamp_to_limits(std::array::from_fn(|i| q[i] + dq[i]));
                let next = self.linearise(&candidate, target);
                if next.cost <= lin.cost {
                    damping = (damping / 3.0).max(1e-9);
                    break Some((candidate, next));
                }
                damping *= 4.0;
                if damping > 1e6 {
                    break None;
                }
            };
            let Some((candidate, next)) = accepted else {
                break;
            };
            let moved = (0..ARM_JOINTS)
                .map(|i| (candidate[i] - q[i]).abs())
                .fold(0.0, f64::max);
            let gain = lin.cost - next.cost;
            q = candidate;
            lin = next;
            if moved < 1e-12 || gain < 1e-24 {
                break;
            }
        }
        let pose = forward_kinematics(&q);
        IkSolution {
            q,
            position_error_m: (target - pose.grip_site).norm(),
            orientation_error_rad: rotation_angle(&pose.gripper.rotation, &GRIPPER_DOWN),
            iterations,
        }
    }
}

/// The damped step `(H + damping I) dq = g` over the joints not pinned at a limit: a joint at
/// a limit whose step would push it further out is held (up to three rounds, the active set).
fn limited_step(
    h: &[[f64; ARM_JOINTS]; ARM_JOINTS],
    g: &[f64; ARM_JOINTS],
    damping: f64,
    q: &[f64; ARM_JOINTS],
) -> [f64; ARM_JOINTS] {
    let mut free = [true; ARM_JOINTS];
    let mut dq = [0.0; ARM_JOINTS];
    for _ in 0..3 {
        let mut index = [0usize; ARM_JOINTS];
        let mut n = 0;
        for i in (0..ARM_JOINTS).filter(|&i| free[i]) {
            index[n] = i;
            n += 1;
        }
        let index = &index[..n];
        let mut a = [[0.0; ARM_JOINTS]; ARM_JOINTS];
        let mut b = [0.0; ARM_JOINTS];
        for (r, &i) in index.iter().enumerate() {
            for (c, &j) in index.iter().enumerate() {
                a[r][c] = h[i][j];
            }
            a[r][r] += damping;
            b[r] = g[i];
        }
        let x = solve_spd(&mut a, &mut b, n);
        dq = [0.0; ARM_JOINTS];
        for (r, &i) in index.iter().enumerate() {
            dq[i] = x[r];
        }
        let mut changed = false;
        for (i, joint) in FETCH_ARM.iter().enumerate() {
            if let Some([lo, hi]) = joint.limits_rad
                && free[i]
                && ((q[i] <= lo && dq[i] < 0.0) || (q[i] >= hi && dq[i] > 0.0))
            {
                free[i] = false;
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    dq
}

/// Solves the leading `n x n` block of the symmetric positive definite system `a x = b` by
/// Cholesky factorisation in place (the damping keeps it positive definite).
fn solve_spd(
    a: &mut [[f64; ARM_JOINTS]; ARM_JOINTS],
    b: &mut [f64; ARM_JOINTS],
    n: usize,
) -> [f64; ARM_JOINTS] {
    let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(u, v)| u * v).sum::<f64>();
    for j in 0..n {
        let d = (a[j][j] - dot(&a[j][..j], &a[j][..j])).max(1e-300).sqrt();
        a[j][j] = d;
        for i in j + 1..n {
            a[i][j] = (a[i][j] - dot(&a[i][..j], &a[j][..j])) / d;
        }
    }
    // L y = b, then L^T x = y.
    for i in 0..n {
        for k in 0..i {
            b[i] -= a[i][k] * b[k];
        }
        b[i] /= a[i][i];
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            b[i] -= a[k][i] * b[k];
        }
        b[i] /= a[i][i];
    }
    *b
}

/// Clamps every limited joint into its range.
fn clamp_to_limits(mut q: [f64; ARM_JOINTS]) -> [f64; ARM_JOINTS] {
    for (qi, joint) in q.iter_mut().zip(&FETCH_ARM) {
        if let Some([lo, hi]) = joint.limits_rad {
            *qi = qi.clamp(lo, hi);
        }
    }
    q
}

/// Angle of the rotation taking `a` to `b`, rad.
fn rotation_angle(a: &Mat3, b: &Mat3) -> f64 {
    let trace: f64 = (0..3).map(|k| a.cols[k].dot(b.cols[k])).sum();
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const BOX_LO: [f64; 3] = [1.19, 0.60, 0.385];
    const BOX_HI: [f64; 3] = [1.49, 0.90, 0.685];

    fn random_target(rng: &mut ChaCha8Rng) -> Vec3 {
        Vec3::from_array(std::array::from_fn(|i| {
            rng.random_range(BOX_LO[i]..=BOX_HI[i])
        }))
    }

    fn within_limits(q: &[f64; ARM_JOINTS]) -> bool {
        q.iter()
            .zip(&FETCH_ARM)
            .all(|(qi, j)| j.limits_rad.is_none_or(|[lo, hi]| *qi >= lo && *qi <= hi))
    }

    /// FetchReach's reset pose puts the grip site at (1.3418, 0.7491, 0.5347)
    /// (rounded to 0.1 mm), gripper pointing down.
    #[test]
    fn forward_kinematics_matches_the_reset_pose() {
        let pose = forward_kinematics(&RESET_Q);
        let expected = Vec3::new(1.3418, 0.7491, 0.5347);
        let error = (pose.grip_site - expected).norm();
        assert!(
            error < 1e-4,
            "grip site {:?}, error {error}",
            pose.grip_site
        );
        // Pointing down to within a milliradian (MuJoCo's weld is soft).
        assert!(rotation_angle(&pose.gripper.rotation, &GRIPPER_DOWN) < 1e-3);
        // The chain's first frame is the pan link's world position.
        assert_eq!(
            pose.joints[0].origin,
            Vec3::from_array(FETCH_ARM[0].offset_m)
        );
    }

    #[test]
    fn ik_reaches_random_targets_within_limits() {
        let ik = IkConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut worst = 0.0f64;
        let mut tilted = 0;
        for _ in 0..300 {
            let target = random_target(&mut rng);
            let s = ik.solve(target);
            assert!(within_limits(&s.q), "{target:?}: {:?}", s.q);
            assert!(s.position_error_m < 1e-3, "{target:?}: {s:?}");
            let reached = forward_kinematics(&s.q).grip_site;
            assert!(((reached - target).norm() - s.position_error_m).abs() < 1e-15);
            worst = worst.max(s.position_error_m);
            if s.orientation_error_rad > 0.02 {
                tilted += 1;
            }
            // Never more than ~12 deg off, even where pointing down is infeasible.
            assert!(s.orientation_error_rad < 0.25, "{target:?}: {s:?}");
        }
        eprintln!(
            "IK over 300 random targets: worst position error {worst:.2e} m, {tilted} tilted"
        );
        // Measured: worst 0.25 mm, 16 tilted; the gripper points down to within 1 deg for most
        // targets.
        assert!(worst < 5e-4, "worst position error {worst} m");
        assert!(
            tilted < 60,
            "{tilted} of 300 targets tilted by more than 0.02 rad"
        );
    }

    #[test]
    fn ik_is_exact_at_the_reset_pose_and_deterministic() {
        let ik = IkConfig::default();
        let target = forward_kinematics(&RESET_Q).grip_site;
        let s = ik.solve(target);
        assert!(s.position_error_m < 1e-5, "{s:?}");
        assert!(
            s.q.iter().zip(&RESET_Q).all(|(a, b)| (a - b).abs() < 0.05),
            "{:?}",
            s.q
        );
        assert_eq!(ik.solve(target), s);
    }

    /// Small end-effector moves (one control step at top speed is ~2 cm) move the joints
    /// little, along straight lines across the whole workspace, corners included.
    #[test]
    fn ik_is_continuous_along_paths() {
        let ik = IkConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let mut worst = 0.0f64;
        let corners = [
            (Vec3::from_array(BOX_LO), Vec3::from_array(BOX_HI)),
            (
                Vec3::new(BOX_LO[0], BOX_LO[1], BOX_HI[2]),
                Vec3::new(BOX_LO[0], BOX_HI[1], BOX_HI[2]),
            ),
            (
                Vec3::new(BOX_HI[0], BOX_LO[1], BOX_HI[2]),
                Vec3::new(BOX_HI[0], BOX_HI[1], BOX_HI[2]),
            ),
        ];
        let paths: Vec<(Vec3, Vec3)> = corners
            .into_iter()
            .chain((0..12).map(|_| (random_target(&mut rng), random_target(&mut rng))))
            .collect();
        for (a, b) in paths {
            let steps = ((b - a).norm() / 0.01).ceil() as usize;
            let mut previous = ik.solve(a).q;
            for k in 1..=steps {
                let q = ik.solve(a + (b - a) * (k as f64 / steps as f64)).q;
                let jump = (0..ARM_JOINTS)
                    .map(|i| (q[i] - previous[i]).abs())
                    .fold(0.0, f64::max);
                worst = worst.max(jump);
                previous = q;
            }
        }
        assert!(worst < 0.2, "a 1 cm move jumped a joint by {worst} rad");
    }
}
