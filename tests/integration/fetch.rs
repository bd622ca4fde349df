//! Fetch-3D end to end: the arm follows the end effector smoothly, the gripper shows where the
//! camera projects it, the table hides what is below its top, and the dataset and the command
//! line take the 3-dimensional env like the 2D ones.

use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::{
    ARM_JOINTS, Env, EnvKind, FETCH_ARM, FRAME_BYTES, FRAME_PX, Fetch, FetchConfig, Frame,
    GRIPPER_LABEL, State, TABLE_LABEL, Vec3, forward_kinematics,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn at(p: [f64; 3]) -> State {
    State {
        q: p.to_vec(),
        qd: vec![0.0; 3],
    }
}

/// Random held actions for 2,000 steps, walls included: the joints never jump, stay inside
/// their limits, and the grip site is where the state says.
#[test]
fn arm_follows_the_end_effector_continuously() {
    let mut env = Fetch::new(FetchConfig::default());
    env.reset(4).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut action = [0.0; 3];
    let mut previous = env.joint_angles();
    let (mut worst_jump, mut worst_residual) = (0.0f64, 0.0f64);
    for k in 0..2000 {
        if k % 4 == 0 {
            action = std::array::from_fn(|_| rng.random_range(-1.0..=1.0));
        }
        env.step(&action);
        let q = env.joint_angles();
        for (i, joint) in FETCH_ARM.iter().enumerate() {
            if let Some([lo, hi]) = joint.limits_rad {
                assert!(
                    q[i] >= lo && q[i] <= hi,
                    "step {k}: {} = {}",
                    joint.name,
                    q[i]
                );
            }
        }
        let jump = (0..ARM_JOINTS)
            .map(|i| (q[i] - previous[i]).abs())
            .fold(0.0, f64::max);
        worst_jump = worst_jump.max(jump);
        previous = q;
        let site = forward_kinematics(&q).grip_site;
        let p = Vec3::from_array([env.state().q[0], env.state().q[1], env.state().q[2]]);
        assert!(((site - p).norm() - env.ik_residual_m()).abs() < 1e-12);
        worst_residual = worst_residual.max(env.ik_residual_m());
    }
    assert!(
        worst_jump < 0.2,
        "a joint jumped {worst_jump} rad in one step"
    );
    assert!(worst_residual < 1e-3, "IK residual {worst_residual} m");
}

/// Pixels (by ray) showing the gripper, with their bounding box and centroid.
fn gripper_pixels(env: &Fetch) -> (Vec<(usize, usize)>, [f64; 2]) {
    let mut pixels = vec![];
    let (mut sc, mut sr) = (0.0, 0.0);
    for row in 0..FRAME_PX {
        for col in 0..FRAME_PX {
            let (x, y) = (col as f64 + 0.5, row as f64 + 0.5);
            if env.pick(x, y).is_some_and(|h| h.label == GRIPPER_LABEL) {
                pixels.push((col, row));
                sc += x;
                sr += y;
            }
        }
    }
    let n = pixels.len().max(1) as f64;
    (pixels, [sc / n, sr / n])
}

#[test]
fn gripper_appears_where_the_camera_projects_it() {
    let mut env = Fetch::new(FetchConfig::default());
    let camera = env.config().camera;
    let mut frame: Frame = [0; FRAME_BYTES];
    for p in [
        [1.3418, 0.7491, 0.5347],
        [1.19, 0.6, 0.685],
        [1.49, 0.9, 0.45],
        [1.49, 0.6, 0.685],
        [1.2, 0.88, 0.46],
        [1.41, 0.7, 0.6],
    ] {
        env.set_state(&at(p)).unwrap();
        env.render(&mut frame);
        let (pixels, [c, r]) = gripper_pixels(&env);
        assert!(pixels.len() >= 12, "{p:?}: {} gripper pixels", pixels.len());
        // The grip site projects inside the gripper's pixels (it sits between the fingers).
        let (pc, pr) = camera.project(Vec3::from_array(p)).unwrap();
        let (c0, c1) = (
            pixels.iter().map(|q| q.0).min(),
            pixels.iter().map(|q| q.0).max(),
        );
        let (r0, r1) = (
            pixels.iter().map(|q| q.1).min(),
            pixels.iter().map(|q| q.1).max(),
        );
        let inside = |v: f64, lo: Option<usize>, hi: Option<usize>| {
            lo.zip(hi)
                .is_some_and(|(lo, hi)| v >= lo as f64 - 1.0 && v <= hi as f64 + 2.0)
        };
        assert!(
            inside(pc, c0, c1) && inside(pr, r0, r1),
            "{p:?}: projection ({pc}, {pr}) outside gripper pixels {c0:?}-{c1:?} x {r0:?}-{r1:?}"
        );
        // The gripper's middle (palm and fingers, 3 cm behind the grip site) projects onto the
        // centroid of its pixels.
        let q = env.joint_angles();
        let g = forward_kinematics(&q).gripper;
        let middle = g.origin + g.rotation.cols[0] * -0.03;
        let (mc, mr) = camera.project(middle).unwrap();
        assert!(
            (mc - c).abs() < 1.5 && (mr - r).abs() < 1.5,
            "{p:?}: centroid ({c}, {r}) vs projection ({mc}, {mr})"
        );
        // And those pixels look like the dark gripper in the frame itself.
        let dark = pixels
            .iter()
            .filter(|&&(col, row)| {
                let px = &frame[(row * FRAME_PX + col) * 3..][..3];
                px.iter().all(|&v| v < 110)
            })
            .count();
        assert!(
            dark * 4 >= pixels.len() * 3,
            "{p:?}: only {dark} of {} gripper pixels are dark",
            pixels.len()
        );
    }
}

/// At the lowest end-effector height the fingertips are 4 cm below the table top: the ray to the
/// grip site meets the table first, and the frame shows the lit table there.
#[test]
fn table_hides_what_is_below_its_top() {
    let mut env = Fetch::new(FetchConfig::default());
    let camera = env.config().camera;
    let p = [1.34, 0.75, 0.385];
    env.set_state(&at(p)).unwrap();
    let mut frame: Frame = [0; FRAME_BYTES];
    env.render(&mut frame);
    for point in [
        Vec3::from_array(p),
        Vec3::new(p[0], p[1] + 0.03, 0.365),
        Vec3::new(p[0], p[1] - 0.03, 0.365),
    ] {
        let (c, r) = camera.project(point).unwrap();
        let hit = env.pick(c, r).unwrap();
        assert_eq!(
            hit.label, TABLE_LABEL,
            "{point:?} is visible through the table"
        );
        assert!((hit.point.z - 0.4).abs() < 1e-9, "{hit:?}");
        let eye = camera.eye();
        assert!((hit.point - eye).norm() < (point - eye).norm());
    }
    let (c, r) = camera.project(Vec3::from_array(p)).unwrap();
    let px = &frame[(r as usize * FRAME_PX + c as usize) * 3..][..3];
    assert!(px.iter().all(|&v| v > 150), "table pixel {px:?}");
    // Raised 5 cm, the fingers clear the table top and show.
    env.set_state(&at([p[0], p[1], p[2] + 0.05])).unwrap();
    assert!(gripper_pixels(&env).0.len() > 20);
}

#[test]
fn sub_pixel_moves_change_pixels() {
    let mut env = Fetch::new(FetchConfig::default());
    let (mut a, mut b): (Frame, Frame) = ([0; FRAME_BYTES], [0; FRAME_BYTES]);
    env.set_state(&at([1.3, 0.75, 0.5])).unwrap();
    env.render(&mut a);
    // 2 mm is about an eighth of a pixel at the table.
    env.set_state(&at([1.302, 0.75, 0.5])).unwrap();
    env.render(&mut b);
    assert!(a != b);
}

#[test]
fn dataset_and_command_line_take_fetch() {
    let config = CollectConfig {
        transitions: 40,
        episode_len: 20,
        ..CollectConfig::new(EnvKind::Fetch, 1)
    };
    assert_eq!(CollectConfig::new(EnvKind::Fetch, 1).transitions, 50_000);
    let data = collect(&config, |_| {}).unwrap();
    assert_eq!((data.action_dim(), data.config_dim()), (3, Some(3)));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("fetch.npz");
    data.save(&path, false).unwrap();
    assert_eq!(Dataset::load(&path).unwrap(), data);
    // Every stored state lies in the workspace box and the frames vary.
    let env = EnvKind::Fetch.make();
    for (i, [lo, hi]) in env.config_ranges().into_iter().enumerate() {
        assert!(
            data.states
                .as_ref()
                .unwrap()
                .index_axis(ndarray::Axis(2), i)
                .iter()
                .all(|&x| x as f64 >= lo - 1e-6 && x as f64 <= hi + 1e-6)
        );
    }
    assert_ne!(data.frame(0, 0), data.frame(0, 20));

    let png = dir.path().join("fetch.png");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_procl"))
        .args(["render", "--env", "fetch", "--frames", "3", "--out"])
        .arg(&png)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
}
