//! The research core (issue 9): the Lyapunov risk must tell an aligned latent from a mirrored
//! one under the default preset's noise handling, and the ablation runner must resume.

use burn::tensor::{Tensor, TensorData};
use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;
use procl::losses::{
    LossConfig, LossInputs, NoiseMode, ResponseGrouping, SignForm, VarianceAxes, procl_loss,
};
use procl::model::{DynamicsConfig, cpu_device, to_vec};
use procl::train::{Method, Preset, TrainConfig};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn point_mass_data() -> Dataset {
    let config = CollectConfig {
        transitions: 4000,
        episode_len: 100,
        ..CollectConfig::new(EnvKind::PointMass, 11)
    };
    collect(&config, |_| {}).unwrap()
}

/// The trainer's Lyapunov term for the synthetic latent `h = map q` (q the true position),
/// averaged over `batches` batches of 256 samples.
fn risk_of_map(data: &Dataset, map: [[f32; 2]; 2], loss: &LossConfig, batches: usize) -> f64 {
    let device = cpu_device();
    let dynamics = DynamicsConfig::new(2).init(&device);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let n = 256;
    let mut total = 0.0;
    for _ in 0..batches {
        let samples: Vec<(usize, usize)> = (0..n)
            .map(|_| {
                (
                    rng.random_range(0..data.episodes()),
                    rng.random_range(1..data.steps()),
                )
            })
            .collect();
        let latent = |dt: isize| {
            let values: Vec<f32> = samples
                .iter()
                .flat_map(|&(e, t)| {
                    let q = data.config(e, (t as isize + dt) as usize);
                    (0..2).map(move |i| map[i][0] * q[0] as f32 + map[i][1] * q[1] as f32)
                })
                .collect();
            Tensor::<2>::from_data(TensorData::new(values, [n, 2]), &device)
        };
        let u: Vec<f32> = samples
            .iter()
            .flat_map(|&(e, t)| [data.actions[[e, t, 0]], data.actions[[e, t, 1]]])
            .collect();
        let normal = |rng: &mut ChaCha8Rng| {
            let v: Vec<f32> = (0..2 * n)
                .map(|_| {
                    let (a, b): (f64, f64) = (
                        rng.random_range(f64::EPSILON..1.0),
                        rng.random_range(0.0..1.0),
                    );
                    ((-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()) as f32
                })
                .collect();
            Tensor::<2>::from_data(TensorData::new(v, [n, 2]), &device)
        };
        let mut permutation: Vec<usize> = (0..n).collect();
        permutation.shuffle(&mut rng);
        let inputs = LossInputs {
            h_prev: latent(-1),
            h_now: latent(0),
            h_next: latent(1),
            u: Tensor::from_data(TensorData::new(u, [n, 2]), &device),
            latent_noise: normal(&mut rng),
            curvature_noise: (normal(&mut rng), normal(&mut rng), normal(&mut rng)),
            permutation,
            ahead: None,
            frame_distances: None,
            decoded_features: None,
            stretch_features: None,
        };
        let terms = procl_loss(loss, &dynamics, inputs, data.meta.control_dt_s);
        total += to_vec(terms.lyap)[0] as f64;
    }
    total / batches as f64
}

#[test]
fn lyapunov_risk_separates_aligned_from_mirrored_latents() {
    let data = point_mass_data();
    let default = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::PointMass).loss;
    assert_eq!(default.noise_mode, NoiseMode::CleanRisk);
    let aligned = risk_of_map(&data, [[1.0, 0.0], [0.0, 1.0]], &default, 4);
    let flipped = risk_of_map(&data, [[-1.0, 0.0], [0.0, 1.0]], &default, 4);
    let swapped = risk_of_map(&data, [[0.0, 1.0], [1.0, 0.0]], &default, 4);
    // Measured 2e-4 aligned vs 1.1e-3 mirrored (numpy on the same formula, docs/method.md).
    assert!(
        aligned < 0.3 * flipped && aligned < 0.3 * swapped,
        "aligned {aligned}, flipped {flipped}, swapped {swapped}"
    );
    assert!(aligned < 1e-3, "aligned risk {aligned} is not near 0");

    // The paper's noise handling at eps = 0.01: the noise enters v amplified by 1/dt, and R has a
    // floor of about Q_v du (eps/dt)^2 / dt_R = 2.5 whatever the latent, which drowns the signal.
    let paper = LossConfig {
        noise_mode: NoiseMode::Paper,
        ..default
    };
    let aligned_noisy = risk_of_map(&data, [[1.0, 0.0], [0.0, 1.0]], &paper, 4);
    let flipped_noisy = risk_of_map(&data, [[-1.0, 0.0], [0.0, 1.0]], &paper, 4);
    assert!(aligned_noisy > 0.5, "noise floor {aligned_noisy}");
    assert!(
        (flipped_noisy - aligned_noisy).abs() < 0.1 * aligned_noisy,
        "{aligned_noisy} vs {flipped_noisy}"
    );
}

#[test]
fn standardised_risk_cannot_be_lowered_by_shrinking_the_latent() {
    let data = point_mass_data();
    let plain = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::PointMass).loss;
    let standardised = LossConfig {
        risk_latent_std: Some(0.1),
        ..plain.clone()
    };
    let risk = |loss: &LossConfig, s: f32, sign: f32| {
        risk_of_map(&data, [[sign * s, 0.0], [0.0, s]], loss, 2)
    };
    // As the paper has it, a 100x smaller latent has a far smaller risk ...
    let (large, small) = (risk(&plain, 1.0, 1.0), risk(&plain, 0.01, 1.0));
    assert!(small < 0.1 * large, "plain risk {large} -> {small}");
    // ... standardised, it has the same one, and it still tells a mirrored latent apart.
    let (large, small) = (
        risk(&standardised, 1.0, 1.0),
        risk(&standardised, 0.01, 1.0),
    );
    assert!(
        (large - small).abs() <= 1e-3 * large.max(1e-9),
        "standardised risk {large} vs {small}"
    );
    let flipped = risk(&standardised, 0.01, -1.0);
    assert!(small < 0.5 * flipped, "aligned {small}, flipped {flipped}");
    // A non-positive scale is refused by name.
    let bad = LossConfig {
        risk_latent_std: Some(0.0),
        ..plain
    };
    let err = bad.validate().unwrap_err().to_string();
    assert!(err.contains("loss.risk_latent_std"), "{err}");
    let bad = LossConfig {
        decorrelation_weight: -1.0,
        ..LossConfig::default()
    };
    let err = bad.validate().unwrap_err().to_string();
    assert!(err.contains("loss.decorrelation_weight"), "{err}");
}

#[test]
fn ablation_grid_runs_resumes_and_writes_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let grid_path = dir.path().join("grid.toml");
    std::fs::write(
        &grid_path,
        r#"
[base]
steps = 4
batch_size = 8
checkpoint_every = 2
orientation_search_every = 2
model = { encoder = { trunk_channels = [4, 4], head = { kind = "soft-argmax", keypoints = 2 } } }
[[cell]]
name = "default"
[[cell]]
name = "pc3"
method = "pc3"
loss = { lambda_r = 0.0 }
"#,
    )
    .unwrap();
    let grid = procl::ablate::Grid::from_toml(&grid_path).unwrap();
    let data = collect(
        &CollectConfig {
            transitions: 120,
            episode_len: 40,
            ..CollectConfig::new(EnvKind::PointMass, 2)
        },
        |_| {},
    )
    .unwrap();
    let mut protocol = procl::eval::ReachConfig::for_env(EnvKind::PointMass, 5);
    protocol.episodes = 2;
    protocol.horizon = 10;
    let out = dir.path().join("ablate");
    let mut fresh = 0;
    let results =
        procl::ablate::run_grid(&grid, &data, 0..1, &protocol, &out, true, |_| fresh += 1).unwrap();
    assert_eq!((results.len(), fresh), (2, 2));
    for file in ["ablation.md", "ablation.json", "ablation.jsonl"] {
        assert!(out.join(file).exists(), "{file} missing");
    }
    let md = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert!(md.contains("| default |") && md.contains("| pc3 |"), "{md}");
    // A second run reads both cells back instead of training them again.
    let checkpoint = out.join("default/seed-0/model.safetensors");
    let before = std::fs::metadata(&checkpoint).unwrap().modified().unwrap();
    let mut redone = 0;
    let again = procl::ablate::run_grid(&grid, &data, 0..1, &protocol, &out, true, |_| redone += 1)
        .unwrap();
    assert_eq!((again.len(), redone), (2, 0));
    assert_eq!(
        std::fs::metadata(&checkpoint).unwrap().modified().unwrap(),
        before
    );
    assert_eq!(again, results);
    // A bad grid is reported with the file and the cell.
    std::fs::write(&grid_path, "[[cell]]\nname = \"x\"\nlearning_rate = -1.0\n").unwrap();
    let bad = procl::ablate::Grid::from_toml(&grid_path).unwrap();
    let err = procl::ablate::run_grid(&bad, &data, 0..1, &protocol, &out, true, |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("cell `x`") && err.contains("learning_rate"),
        "{err}"
    );
}

/// The soft-argmax head with `keypoints`, a tanh layer of `hidden` (0: none), Cartesian or
/// polar coordinates, and no `(x, y)` beside polar ones.
fn keypoint_head(keypoints: usize, hidden: usize, polar: bool) -> procl::model::EncoderHead {
    procl::model::EncoderHead::SoftArgmax {
        keypoints,
        hidden,
        polar,
        with_cartesian: false,
        pairwise_angles: false,
        linear_base: false,
    }
}

/// The polar tanh head of `hidden` units with the angles between keypoints (stops 17-22).
fn pairwise_head(hidden: usize) -> procl::model::EncoderHead {
    procl::model::EncoderHead::SoftArgmax {
        keypoints: 16,
        hidden,
        polar: true,
        with_cartesian: false,
        pairwise_angles: true,
        linear_base: false,
    }
}

/// Stop 18's pairwise design: the pairwise head, the pairs entering from 0, the fade at the cut.
fn straight_pairwise_faded(c: &mut TrainConfig) {
    c.model.encoder.head = pairwise_head(32);
    c.model.encoder.pairwise_init_scale = 0.0;
    c.model.encoder.polar_cut_fade_deg = 15.0;
}

#[test]
fn shipped_ablation_grids_resolve_for_their_envs() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("ablation");
    for (file, env) in [
        ("point-mass.toml", EnvKind::PointMass),
        ("sharpness.toml", EnvKind::PointMass),
        ("reacher.toml", EnvKind::Reacher),
        ("fetch.toml", EnvKind::Fetch),
    ] {
        let grid = procl::ablate::Grid::from_toml(&root.join(file)).unwrap();
        let configs = grid
            .cell_configs(env)
            .unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(configs.len(), grid.cells.len());
        assert!(configs.iter().all(|(_, c)| c.env == env));
    }
    // The reacher grid's variance-floor cells carry the floor through to the loss.
    let grid = procl::ablate::Grid::from_toml(&root.join("reacher.toml")).unwrap();
    let configs = grid.cell_configs(EnvKind::Reacher).unwrap();
    let (_, floor) = configs
        .iter()
        .find(|(name, _)| name == "tanh-head_std1_floor=10_steps=1200")
        .unwrap();
    assert_eq!(floor.loss.variance_floor, Some(1.0));
    assert_eq!(floor.steps, 1200);
    assert_eq!(floor.model.encoder.init_latent_std, Some(1.0));
    // The reacher's procl preset is the design the stop-29 sign-term cell measured: stop 15's
    // with no velocity term in `V`, ten times its risk weight (stop 20), stop 18's pairwise
    // angles over 32x32 cells (stop 22; the stop-21 cell), and the sign term (stop 30).
    let cell = |name: &str| {
        let (_, cell) = configs.iter().find(|(n, _)| n == name).unwrap();
        cell.clone()
    };
    let new_design = cell("stop15_polar_tanh-head_action-response_risk_latent_std=1_kp=1");
    let stop20_design = cell("stop20_preset_q_v=0_lambda_r=1");
    let stop22_design = cell(
        "stop21_preset_pairwise_angles_pairwise_init_scale=0_cut_fade=15_trunk_second_stride=1",
    );
    // The preset since stop 32: the sign term with its singular-value floor.
    let mut preset = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
    preset.steps = 1200;
    assert_eq!(
        preset,
        cell("stop32_preset_action_response_singular_floor=0.25")
    );
    // A variant cell is its base configuration with one change.
    let assert_variant = |base: &TrainConfig, change: &dyn Fn(&mut TrainConfig), name: &str| {
        let mut expected = base.clone();
        change(&mut expected);
        assert_eq!(expected, cell(name), "{name}");
    };
    // Stop 32's cluster groups on the new preset.
    assert_variant(
        &preset,
        &|c| c.loss.action_response_grouping = ResponseGrouping::Clusters,
        "stop32_preset_action_response_grouping=clusters",
    );
    // Stops 30-31's preset: the sign term alone.
    let mut sign_preset = preset;
    sign_preset.loss.action_response_singular_floor = 0.0;
    assert_eq!(
        sign_preset,
        cell("stop29_preset_action_response_sign_weight=3_k=5_velocity_regions=6")
    );
    // Stop 30's variants of the preset: the floor on the principal axes, the groups as
    // clusters, and both together (later in stop 30).
    assert_variant(
        &sign_preset,
        &|c| c.loss.variance_axes = VarianceAxes::Principal,
        "stop30_preset_variance_axes=principal",
    );
    assert_variant(
        &sign_preset,
        &|c| c.loss.action_response_grouping = ResponseGrouping::Clusters,
        "stop30_preset_action_response_grouping=clusters",
    );
    assert_variant(
        &sign_preset,
        &|c| {
            c.loss.action_response_grouping = ResponseGrouping::Clusters;
            c.loss.variance_axes = VarianceAxes::Principal;
        },
        "stop30_preset_variance_axes=principal_grouping=clusters",
    );
    // Stop 31: the sign term's eigenvalue form alone, and twelve groups.
    assert_variant(
        &sign_preset,
        &|c| c.loss.action_response_sign_form = SignForm::Eigenvalues,
        "stop31_preset_action_response_sign_form=eigenvalues",
    );
    assert_variant(
        &sign_preset,
        &|c| c.loss.action_response_regions = 12,
        "stop31_preset_action_response_regions=12",
    );
    // Stops 22-29's preset is the same without the sign term's four fields.
    let mut preset = sign_preset.clone();
    preset.loss.action_response_sign_weight = 0.0;
    preset.loss.action_response_horizon = 1;
    preset.loss.action_response_velocity = false;
    preset.loss.action_response_regions = 3;
    assert_eq!(preset, stop22_design);
    let stop20_preset = |c: &mut TrainConfig| (c.loss.q_v, c.loss.lambda_r) = (0.0, 1.0);
    let mut expected = new_design.clone();
    stop20_preset(&mut expected);
    assert_eq!(expected, stop20_design);
    // Stop 22's networks, for ProCL and PC3 alike.
    let stop22_networks = |c: &mut TrainConfig| {
        straight_pairwise_faded(c);
        c.model.encoder.trunk_second_stride = 1;
    };
    stop22_networks(&mut expected);
    assert_eq!(expected, stop22_design);
    // PC3 has no risk: its preset is the stop-15 cell's with stop 22's networks.
    let mut pc3_preset = TrainConfig::preset(Preset::Procl, Method::Pc3, EnvKind::Reacher);
    pc3_preset.steps = 1200;
    let stop22_pc3 =
        cell("stop22_pc3_pairwise_angles_pairwise_init_scale=0_cut_fade=15_trunk_second_stride=1");
    assert_eq!(pc3_preset, stop22_pc3);
    let mut expected = cell("stop15_pc3_polar_tanh-head_action-response_risk_latent_std=1_kp=1");
    stop22_networks(&mut expected);
    assert_eq!(expected, stop22_pc3);
    // Stop 23: the preset since stop 22 with the cut at the gap's centre, and with the turn term.
    let mut expected = preset.clone();
    expected.model.encoder.polar_cut_deg = Some(180.0);
    assert_eq!(expected, cell("stop23_preset_cut=180"));
    let mut expected = preset.clone();
    expected.loss.action_response_turn_weight = 10.0;
    expected.loss.action_response_horizon = 10;
    expected.loss.action_response_velocity = true;
    assert_eq!(
        expected,
        cell("stop23_preset_action_response_turn_weight=10_k=10_velocity")
    );
    // Stop 24: the turn term at weight 3, then with the floor on the principal axes.
    expected.loss.action_response_turn_weight = 3.0;
    assert_eq!(
        expected,
        cell("stop24_preset_action_response_turn_weight=3_k=10_velocity")
    );
    let mut separated = expected.clone();
    expected.loss.variance_axes = VarianceAxes::Principal;
    assert_eq!(
        expected,
        cell("stop24_preset_action_response_turn_weight=3_k=10_velocity_variance_axes=principal")
    );
    // Stop 25: the turn term at weight 3 and the separation term.
    separated.loss.separation_weight = 100.0;
    separated.loss.separation_ratio = 0.1;
    assert_eq!(
        separated,
        cell("stop25_preset_action_response_turn_weight=3_k=10_velocity_separation=100_rho=0.1")
    );
    // Stop 26: the turn term at weight 3 and the feature decoder.
    let mut decoded = separated.clone();
    (
        decoded.loss.separation_weight,
        decoded.loss.separation_ratio,
    ) = (0.0, 0.1);
    (decoded.loss.decoder_weight, decoded.loss.decoder_noise) = (3.0, 0.05);
    decoded.model.feature_decoder_width = 64;
    assert_eq!(
        decoded,
        cell(
            "stop26_preset_action_response_turn_weight=3_k=10_velocity_decoder=3_width=64_noise=0.05"
        )
    );
    decoded.loss.decoder_weight = 1.0;
    (
        decoded.loss.decoder_standardise,
        decoded.loss.decoder_head_only,
    ) = (true, true);
    assert_eq!(
        decoded,
        cell(
            "stop26_preset_action_response_turn_weight=3_k=10_velocity_decoder=1_standardised_head-only"
        )
    );
    // Stop 27: the turn term at weight 3 and the local-stretch term.
    let mut stretched = separated.clone();
    stretched.loss.separation_weight = 0.0;
    (stretched.loss.stretch_weight, stretched.loss.stretch_ratio) = (10.0, 0.25);
    assert_eq!(
        stretched,
        cell("stop27_preset_action_response_turn_weight=3_k=10_velocity_stretch=10_rho=0.25")
    );
    // Each stop-14 and stop-15 cell is the stop-13 design (the preset until stop 15) at 1200
    // steps plus its changes.
    let stop13_design = cell("tanh-head_std1_floor=10");
    // `[base]` undoes stop 15's additions, so the stop-13 cell is that design exactly.
    let mut undone = preset.clone();
    undone.steps = stop13_design.steps;
    undone.orientation_criterion = procl::orientation::OrientationCriterion::Risk;
    undone.loss.risk_latent_std = None;
    (undone.loss.kp, undone.loss.kd, undone.loss.lambda_r) = (10.0, 2.0, 10.0);
    undone.loss.q_v = 0.1;
    undone.model.encoder.head = keypoint_head(16, 32, false);
    undone.model.encoder.pairwise_init_scale = 1.0;
    undone.model.encoder.polar_cut_fade_deg = 0.0;
    undone.model.encoder.trunk_second_stride = 2;
    assert_eq!(undone, stop13_design);
    let stop14 = |name: &str| {
        let mut expected = stop13_design.clone();
        expected.steps = 1200;
        (expected, cell(name))
    };
    let (mut expected, cell) = stop14("stop14_action-response");
    expected.orientation_criterion = procl::orientation::OrientationCriterion::ActionResponse;
    assert_eq!(expected, cell);
    let (mut expected, cell) = stop14("stop14_risk_latent_std=0.1");
    expected.loss.risk_latent_std = Some(0.1);
    assert_eq!(expected, cell);
    // Stop 15: the polar head with a linear output, oriented by the action response.
    let (mut expected, cell) = stop14("stop15_polar_action-response_risk_latent_std=0.1");
    expected.orientation_criterion = procl::orientation::OrientationCriterion::ActionResponse;
    expected.loss.risk_latent_std = Some(0.1);
    expected.model.encoder.head = keypoint_head(16, 0, true);
    assert_eq!(expected, cell);
    // The new preset is the stop-13 design plus the polar head, the action response and the
    // gain-matched standardised risk.
    let mut expected = stop13_design.clone();
    expected.steps = 1200;
    expected.orientation_criterion = procl::orientation::OrientationCriterion::ActionResponse;
    expected.loss.risk_latent_std = Some(1.0);
    expected.loss.kp = 1.0;
    expected.loss.kd = 0.2;
    expected.loss.lambda_r = 0.1;
    expected.model.encoder.head = keypoint_head(16, 32, true);
    assert_eq!(expected, new_design);
    // Stops 16-18: each cell is the preset plus the one change its name says.
    let preset_plus = |name: &str, change: &dyn Fn(&mut TrainConfig)| {
        let mut expected = new_design.clone();
        change(&mut expected);
        let (_, got) = configs.iter().find(|(n, _)| n == name).unwrap();
        assert_eq!(&expected, got, "{name}");
    };
    preset_plus("stop16_preset_orientation_tolerance=0.8", &|c| {
        c.orientation_tolerance = 0.8
    });
    preset_plus("stop16_preset_variance_axes=principal", &|c| {
        c.loss.variance_axes = VarianceAxes::Principal
    });
    preset_plus("stop16_preset_batch_group=8x8", &|c| {
        (c.batch_group_size, c.batch_group_window) = (8, 8)
    });
    preset_plus("stop16_preset_full_covariance", &|c| {
        c.model.dynamics.full_covariance = true
    });
    // `variance_floor = 0` leaves the hinge `max(0, 0 - std)` at 0: the floor is off.
    preset_plus("stop16_preset_no_floor", &|c| {
        c.loss.variance_floor = Some(0.0)
    });
    preset_plus("stop16_preset_no_floor_keypoints=32", &|c| {
        c.loss.variance_floor = Some(0.0);
        c.model.encoder.head = keypoint_head(32, 32, true);
    });
    preset_plus("stop16_preset_lambda_r=0.3", &|c| c.loss.lambda_r = 0.3);
    preset_plus("stop16_preset_lambda_r=1", &|c| c.loss.lambda_r = 1.0);
    preset_plus("stop16_preset_keypoint_upsample=4", &|c| {
        c.model.encoder.keypoint_upsample = 4
    });
    preset_plus("stop16_preset_keypoint_upsample=2", &|c| {
        c.model.encoder.keypoint_upsample = 2
    });
    preset_plus("stop16_preset_with_cartesian", &|c| {
        c.model.encoder.head = procl::model::EncoderHead::SoftArgmax {
            keypoints: 16,
            hidden: 32,
            polar: true,
            with_cartesian: true,
            pairwise_angles: false,
            linear_base: false,
        };
    });
    // The constant diagonal input's gains fix the orientation, so its cell turns the search off.
    preset_plus("stop17_preset_pairwise_angles", &|c| {
        c.model.encoder.head = pairwise_head(32)
    });
    preset_plus("stop17_preset_pairwise_angles_linear", &|c| {
        c.model.encoder.head = pairwise_head(0)
    });
    preset_plus("stop17_preset_constant_diagonal_input=50", &|c| {
        c.orientation_search_every = 0;
        c.model.dynamics.input =
            procl::model::DynamicsInput::ConstantDiagonal { initial_gain: 50.0 };
    });
    preset_plus(
        "stop17_preset_constant_diagonal_input=50_action-response",
        &|c| {
            c.model.dynamics.input =
                procl::model::DynamicsInput::ConstantDiagonal { initial_gain: 50.0 }
        },
    );
    preset_plus("stop17_preset_pairwise_angles_no_floor", &|c| {
        c.model.encoder.head = pairwise_head(32);
        c.loss.variance_floor = Some(0.0);
    });
    preset_plus("stop17_preset_action_response_weight=3", &|c| {
        c.loss.action_response_weight = 3.0
    });
    preset_plus(
        "stop17_preset_pairwise_angles_action_response_weight=3",
        &|c| {
            c.model.encoder.head = pairwise_head(32);
            c.loss.action_response_weight = 3.0;
        },
    );
    preset_plus(
        "stop17_preset_pairwise_angles_action_response_weight=30",
        &|c| {
            c.model.encoder.head = pairwise_head(32);
            c.loss.action_response_weight = 30.0;
        },
    );
    preset_plus("stop17_preset_pairwise_angles_lambda_r=1", &|c| {
        c.model.encoder.head = pairwise_head(32);
        c.loss.lambda_r = 1.0;
    });
    preset_plus("stop17_preset_transition_init_std=0.02", &|c| {
        c.model.dynamics.init_std = 0.02
    });
    preset_plus("stop18_preset_action_response_k=10_weight=3", &|c| {
        c.loss.action_response_weight = 3.0;
        c.loss.action_response_horizon = 10;
    });
    preset_plus(
        "stop18_preset_pairwise_angles_action_response_k=10_weight=3",
        &|c| {
            c.model.encoder.head = pairwise_head(32);
            c.loss.action_response_weight = 3.0;
            c.loss.action_response_horizon = 10;
        },
    );
    preset_plus(
        "stop18_preset_action_response_velocity_k=5_weight=3",
        &|c| {
            c.loss.action_response_weight = 3.0;
            c.loss.action_response_horizon = 5;
            c.loss.action_response_velocity = true;
        },
    );
    preset_plus(
        "stop18_preset_pairwise_angles_action_response_velocity_k=10_weight=10",
        &|c| {
            c.model.encoder.head = pairwise_head(32);
            c.loss.action_response_weight = 10.0;
            c.loss.action_response_horizon = 10;
            c.loss.action_response_velocity = true;
        },
    );
    preset_plus("stop18_preset_pairwise_angles_lambda_cpc=0.1", &|c| {
        c.model.encoder.head = pairwise_head(32);
        c.loss.lambda_cpc = 0.1;
    });
    preset_plus(
        "stop18_preset_pairwise_angles_no_orientation_search",
        &|c| {
            c.model.encoder.head = pairwise_head(32);
            c.orientation_search_every = 0;
        },
    );
    preset_plus(
        "stop18_preset_pairwise_angles_pairwise_init_scale=0",
        &|c| {
            c.model.encoder.head = pairwise_head(32);
            c.model.encoder.pairwise_init_scale = 0.0;
        },
    );
    // Stop 18's pairwise design: pairwise angles started at 0, the angle faded before the cut.
    preset_plus(
        "stop18_preset_pairwise_angles_pairwise_init_scale=0_cut_fade=15",
        &straight_pairwise_faded,
    );
    preset_plus(
        "stop18_preset_pairwise_angles_pairwise_init_scale=0_cut_fade=15_cut=180",
        &|c| {
            straight_pairwise_faded(c);
            c.model.encoder.polar_cut_deg = Some(180.0);
        },
    );
    preset_plus("stop18_preset_cut=180", &|c| {
        c.model.encoder.polar_cut_deg = Some(180.0)
    });
    preset_plus("stop18_preset_cut_fade=15", &|c| {
        c.model.encoder.polar_cut_fade_deg = 15.0
    });
    preset_plus("stop19_preset_relative_angles", &|c| {
        c.model.encoder.relative_angles = true
    });
    preset_plus("stop19_preset_batch=256", &|c| c.batch_size = 256);
    // Stop 20: the risk's velocity term, and the diagnostic state supervision.
    preset_plus("stop20_preset_q_v=0", &|c| c.loss.q_v = 0.0);
    preset_plus("stop20_preset_q_v=0_lambda_r=3", &|c| {
        (c.loss.q_v, c.loss.lambda_r) = (0.0, 3.0)
    });
    preset_plus(
        "stop20_preset_q_v=0_lambda_r=1_pairwise_angles_pairwise_init_scale=0_cut_fade=15",
        &|c| {
            stop20_preset(c);
            straight_pairwise_faded(c);
        },
    );
    preset_plus("stop20_preset_q_v=0_lambda_r=1_cut=180", &|c| {
        stop20_preset(c);
        c.model.encoder.polar_cut_deg = Some(180.0);
    });
    // Stop 21: the stop-20 preset at twice the steps, and 32x32 keypoint cells.
    preset_plus("stop21_preset_steps=2400", &|c| {
        stop20_preset(c);
        c.steps = 2400;
    });
    preset_plus("stop21_preset_trunk_second_stride=1", &|c| {
        stop20_preset(c);
        c.model.encoder.trunk_second_stride = 1;
    });
    preset_plus(
        "stop21_preset_pairwise_angles_pairwise_init_scale=0_cut_fade=15_trunk_second_stride=1",
        &|c| {
            stop20_preset(c);
            straight_pairwise_faded(c);
            c.model.encoder.trunk_second_stride = 1;
        },
    );
    // Stop 22: the base angle a linear map of the keypoints' angles, at the gap's centre.
    preset_plus(
        "stop22_preset_pairwise_angles_linear_base_cut=180_cut_fade=15_trunk_second_stride=1",
        &|c| {
            stop20_preset(c);
            c.model.encoder.head = procl::model::EncoderHead::SoftArgmax {
                keypoints: 16,
                hidden: 32,
                polar: true,
                with_cartesian: false,
                pairwise_angles: true,
                linear_base: true,
            };
            c.model.encoder.polar_cut_deg = Some(180.0);
            c.model.encoder.polar_cut_fade_deg = 15.0;
            c.model.encoder.trunk_second_stride = 1;
        },
    );
    let supervised = |c: &mut TrainConfig, weight: f64| {
        c.orientation_search_every = 0;
        c.loss.state_supervision_weight = weight;
    };
    preset_plus("stop20_stop15_preset_state_supervision=10", &|c| {
        supervised(c, 10.0)
    });
    preset_plus(
        "stop20_stop15_preset_state_supervision=10_pairwise_angles",
        &|c| {
            supervised(c, 10.0);
            c.model.encoder.head = pairwise_head(32);
        },
    );
    preset_plus(
        "stop20_stop15_preset_state_supervision=10_lambda_r=0",
        &|c| {
            supervised(c, 10.0);
            c.loss.lambda_r = 0.0;
        },
    );
    // PC3's terms and the regression with the pairwise head: the supervised ceiling.
    let supervised_pc3_pairwise = |c: &mut TrainConfig| {
        supervised(c, 10.0);
        (c.loss.lambda_r, c.loss.q_v) = (0.0, 0.0);
        c.model.encoder.head = pairwise_head(32);
    };
    preset_plus(
        "stop20_stop15_preset_state_supervision=10_lambda_r=0_pairwise_angles",
        &supervised_pc3_pairwise,
    );
    preset_plus(
        "stop21_state_supervision=10_lambda_r=0_pairwise_angles_trunk_second_stride=1",
        &|c| {
            supervised_pc3_pairwise(c);
            c.model.encoder.trunk_second_stride = 1;
        },
    );
    let supervision_only = |c: &mut TrainConfig| {
        supervised(c, 1.0);
        (c.loss.lambda_pc3, c.loss.lambda_r) = (0.0, 0.0);
        c.loss.variance_floor = Some(0.0);
    };
    preset_plus("stop20_state_supervision_only", &|c| supervision_only(c));
    preset_plus("stop20_state_supervision_only_pairwise_angles", &|c| {
        supervision_only(c);
        c.model.encoder.head = pairwise_head(32);
    });
    preset_plus("stop20_state_supervision_only_mlp_head", &|c| {
        supervision_only(c);
        c.model.encoder.head = procl::model::EncoderHead::Mlp { hidden: 256 };
    });
    preset_plus(
        "stop19_preset_relative_angles_reference_radius=0.35_cut=180",
        &|c| {
            c.model.encoder.relative_angles = true;
            c.model.encoder.relative_reference_radius = 0.35;
            c.model.encoder.polar_cut_deg = Some(180.0);
        },
    );
    preset_plus(
        "stop18_pc3_pairwise_angles_pairwise_init_scale=0_cut_fade=15",
        &|c| {
            c.method = Method::Pc3;
            c.loss.lambda_r = 0.0;
            straight_pairwise_faded(c);
        },
    );
    // Fetch: the `action-response` cells are the presets of both latent methods, and the
    // `risk-search` cells the stop-13 rule they replaced.
    let grid = procl::ablate::Grid::from_toml(&root.join("fetch.toml")).unwrap();
    let configs = grid.cell_configs(EnvKind::Fetch).unwrap();
    // Cells measured before stop 25 keep that preset's Kd = 2 (`Some`); the others are the
    // preset as it is (`None`).
    for (name, method, kd) in [
        ("action-response", Method::Procl, None),
        ("pc3_action-response", Method::Pc3, None),
        ("stop14_kd=2", Method::Procl, Some(2.0)),
        ("pc3_stop14_kd=2", Method::Pc3, Some(2.0)),
    ] {
        let (_, cell) = configs.iter().find(|(n, _)| n == name).unwrap();
        let mut expected = TrainConfig::preset(Preset::Procl, method, EnvKind::Fetch);
        expected.steps = cell.steps;
        if let Some(kd) = kd {
            expected.loss.kd = kd;
        }
        assert_eq!(&expected, cell, "{name}");
    }
    let (_, risk) = configs.iter().find(|(n, _)| n == "risk-search").unwrap();
    assert_eq!((risk.orientation_margin, risk.orientation_streak), (0.0, 3));
    assert_eq!(risk.loss.kd, 2.0);
    // Stop 23: the Fetch preset of then without the velocity term in `V`.
    let (_, q_v_0) = configs.iter().find(|(n, _)| n == "stop23_q_v=0").unwrap();
    let mut expected = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Fetch);
    expected.steps = q_v_0.steps;
    expected.loss.kd = 2.0;
    expected.loss.q_v = 0.0;
    assert_eq!(&expected, q_v_0);
    // Stop 24: a lighter velocity term.
    let (_, q_v_003) = configs
        .iter()
        .find(|(n, _)| n == "stop24_q_v=0.03")
        .unwrap();
    expected.loss.q_v = 0.03;
    assert_eq!(&expected, q_v_003);
}
