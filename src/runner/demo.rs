//! The one-command demo: point-mass pixels -> dataset -> ProCL and PC3 -> latent PD vs the oracle
//! -> `report.html`. Stages whose outputs exist are reused, so an interrupted demo resumes.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::data::CollectConfig;
use crate::envs::EnvKind;
use crate::error::{Error, Result};
use crate::eval::{
    LatentDiagnostics, MethodSummary, ReachConfig, ReachReport, evaluate_run, save_reach_plot,
    write_env_diagnostics,
};
use crate::runner::stages::{
    Outcome, ThrottledLine, collect_or_reuse, reach_protocol, set_budget, shrink_networks,
    train_or_reuse, training_seconds,
};
use crate::train::{Method, Preset, RunPaths, TrainConfig};

/// Budgets of a demo run.
#[derive(Debug, Clone)]
pub struct DemoConfig {
    pub out: PathBuf,
    pub transitions: usize,
    pub episode_len: usize,
    pub train_steps: u64,
    pub batch_size: usize,
    pub eval_episodes: usize,
    pub eval_horizon: Option<usize>,
    pub seed: u64,
    /// Shrinks the encoder (for the smoke test).
    pub tiny_model: bool,
}

impl DemoConfig {
    /// The README's demo: 10k transitions, both methods trained with the default preset for 600
    /// steps (about 40 s each on 2 cores; 500 steps already reached every goal).
    pub fn full(out: impl Into<PathBuf>) -> Self {
        Self {
            out: out.into(),
            transitions: 10_000,
            episode_len: 100,
            train_steps: 600,
            batch_size: 128,
            eval_episodes: 50,
            eval_horizon: None,
            seed: 0,
            tiny_model: false,
        }
    }

    /// The same pipeline on a tiny budget (seconds), for CI.
    pub fn quick(out: impl Into<PathBuf>) -> Self {
        Self {
            transitions: 400,
            episode_len: 50,
            train_steps: 15,
            batch_size: 16,
            eval_episodes: 3,
            eval_horizon: Some(60),
            tiny_model: true,
            ..Self::full(out)
        }
    }
}

/// One row of the demo's results.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoRow {
    pub summary: MethodSummary,
    pub diagnostics: Option<LatentDiagnostics>,
    pub train_seconds: Option<f64>,
}

/// What the demo produced.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoResult {
    pub rows: Vec<DemoRow>,
    pub report_html: PathBuf,
    pub protocol: ReachConfig,
}

/// Runs the demo; `log` receives one line per stage.
pub fn run_demo(config: &DemoConfig, mut log: impl FnMut(&str)) -> Result<DemoResult> {
    let env = EnvKind::PointMass;
    let _writer = crate::fsutil::FolderLock::acquire(&config.out)?;
    let data_path = config.out.join("point-mass.npz");
    let clock = Instant::now();
    let collect_config = CollectConfig {
        transitions: config.transitions,
        episode_len: config.episode_len,
        ..CollectConfig::new(env, config.seed)
    };
    let (dataset, outcome) = collect_or_reuse(&collect_config, &data_path, |_| {})?;
    log(&match outcome {
        Outcome::Reused => format!("reusing {}", data_path.display()),
        Outcome::Ran => format!(
            "collected {} transitions in {:.1} s",
            dataset.transitions(),
            clock.elapsed().as_secs_f64()
        ),
    });

    let protocol = reach_protocol(env, config.eval_episodes, config.eval_horizon);
    let mut rows = vec![];
    let mut oracle = None;
    for method in [Method::Procl, Method::Pc3] {
        let name = method.dir_name();
        let run = RunPaths::new(config.out.join(name));
        let mut train_config = TrainConfig::preset(Preset::Procl, method, env);
        train_config.seed = config.seed;
        set_budget(
            &mut train_config,
            config.train_steps,
            Some(config.batch_size),
        );
        if config.tiny_model {
            shrink_networks(&mut train_config);
        }
        let mut every_30_s = ThrottledLine::new(std::time::Duration::from_secs(30));
        let steps = train_config.steps;
        let outcome = train_or_reuse(&train_config, &dataset, &run, |step, values| {
            if let Some(eta) = every_30_s.due(step, steps) {
                log(&format!(
                    "training {name}: step {step}/{steps}, eta {eta}, {values}"
                ));
            }
        })?;
        let train_seconds = (outcome == Outcome::Ran)
            .then(|| training_seconds(&run))
            .flatten();
        log(&match outcome {
            Outcome::Ran => format!(
                "trained {name}: {} steps in {:.0} s",
                train_config.steps,
                train_seconds.unwrap_or(f64::NAN)
            ),
            Outcome::Reused => format!("reusing trained {name} in {}", run.dir.display()),
        });
        let diagnostics = write_env_diagnostics(&run)?;
        let report: ReachReport = evaluate_run(&run, &protocol, |_| {})?;
        let mut methods = report.methods.into_iter();
        if let Some(latent) = methods.next() {
            log(&format!(
                "evaluated {name}: success {:.0}%, final distance {:.4} m, R^2 {:.3}",
                100.0 * latent.success_rate,
                latent.final_mean,
                diagnostics.linear_r2
            ));
            rows.push(DemoRow {
                summary: latent,
                diagnostics: Some(diagnostics),
                train_seconds,
            });
        }
        oracle = methods.next();
    }
    if let Some(oracle) = oracle {
        rows.push(DemoRow {
            summary: oracle,
            diagnostics: None,
            train_seconds: None,
        });
    }
    let summaries: Vec<MethodSummary> = rows.iter().map(|r| r.summary.clone()).collect();
    let figure = config.out.join("reach_all.png");
    save_reach_plot(
        &figure,
        "point mass: goal reaching from pixels",
        &summaries,
        protocol.success_threshold,
        &protocol.distance_unit,
    )?;
    let report_html = config.out.join("report.html");
    write_report(&report_html, &rows, &protocol)?;
    let result = DemoResult {
        rows,
        report_html,
        protocol,
    };
    let json_path = config.out.join("summary.json");
    crate::fsutil::write_json(&json_path, &result)?;
    Ok(result)
}

fn write_report(path: &Path, rows: &[DemoRow], protocol: &ReachConfig) -> Result<()> {
    let mut table = String::new();
    for row in rows {
        let s = &row.summary;
        let time = s.control_time_us_p50.map_or("-".into(), |p50| {
            format!(
                "{p50:.0} / {:.0}",
                s.control_time_us_p99.unwrap_or(f64::NAN)
            )
        });
        let r2 = row
            .diagnostics
            .as_ref()
            .map_or("-".into(), |d| format!("{:.3}", d.linear_r2));
        let det = row
            .diagnostics
            .as_ref()
            .and_then(|d| d.config_to_latent_det)
            .map_or("-".into(), |d| format!("{d:.2}"));
        let train = row.train_seconds.map_or("-".into(), |t| format!("{t:.0}"));
        table.push_str(&format!(
            "<tr><td>{}</td><td>{:.0}%</td><td>{:.4} &plusmn; {:.4}</td><td>{time}</td><td>{r2}</td><td>{det}</td><td>{train}</td></tr>\n",
            s.method,
            100.0 * s.success_rate,
            s.final_mean,
            s.final_std
        ));
    }
    let html = format!(
        r#"<!doctype html><html><head><meta charset="utf-8"><title>procl demo</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto}}td,th{{padding:4px 10px;border-bottom:1px solid #ddd}}img{{max-width:100%}}</style></head><body>
<h1>procl demo: PD control from pixels on Point mass-2D</h1>
<p>{episodes} episodes from random starts to random goals (goal given as an image), {horizon} steps each;
success = final distance &lt; {threshold} {unit}. Latent PD uses Kp = 10, Kd = 2 on the learned latent.</p>
<table><tr><th>method</th><th>success</th><th>final distance</th><th>control time p50 / p99 (&micro;s)</th><th>R&sup2; of q from h</th><th>det(q&rarr;h)</th><th>training (s)</th></tr>
{table}</table>
<h2>Distance to goal</h2><img src="reach_all.png">
<h2>ProCL</h2><p>Latent map (h coloured by true position), PD trajectories in the latent plane, one episode beside its goal image.</p>
<img src="procl/latent_map.png" width="45%"> <img src="procl/latent_traj.png" width="45%"><br><img src="procl/episode.gif">
<h2>PC3 (same networks, &lambda;<sub>R</sub> = 0)</h2>
<img src="pc3/latent_map.png" width="45%"> <img src="pc3/latent_traj.png" width="45%"><br><img src="pc3/episode.gif">
</body></html>
"#,
        episodes = protocol.episodes,
        horizon = protocol.horizon,
        threshold = protocol.success_threshold,
        unit = protocol.distance_unit,
    );
    crate::write_atomically(path, true, |w| {
        std::io::Write::write_all(w, html.as_bytes()).map_err(|e| Error::io(path, e))
    })
}
