//! Demonstration trajectories for tracking: smooth reference paths in configuration space
//! (circle, figure-eight, random spline), followed by an expert and stored as a dataset.
//!
//! The expert is PD on the true state with the path's velocity as feed-forward target
//! (`u = Kp (q_ref - q) + Kd (qd_ref - qd)`, the oracle gains). What is stored is what the
//! expert achieved: dynamically feasible states, the actions that produced them and the frames
//! rendered from them, in the same NPZ layout as random-control data (`source` says
//! `demonstration:<shape>`).

use std::f64::consts::TAU;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::oracle_gains;
use crate::data::{Dataset, Recording};
use crate::envs::{EnvConfig, EnvKind, State};
use crate::error::{Error, Result};

/// The family of reference paths.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PathShape {
    /// One loop of a circle (an ellipse in joint space when the ranges differ) per episode.
    Circle,
    /// A 1:2 Lissajous figure-eight, one loop per episode.
    FigureEight,
    /// A Catmull-Rom spline through a random walk of waypoints, one every 125 steps.
    Spline,
}

impl PathShape {
    pub fn name(self) -> &'static str {
        match self {
            PathShape::Circle => "circle",
            PathShape::FigureEight => "figure-eight",
            PathShape::Spline => "spline",
        }
    }
}

impl std::str::FromStr for PathShape {
    type Err = Error;
    fn from_str(name: &str) -> Result<Self> {
        match name {
            "circle" => Ok(PathShape::Circle),
            "figure-eight" => Ok(PathShape::FigureEight),
            "spline" => Ok(PathShape::Spline),
            other => Err(Error::config(
                "shape",
                format!("unknown path shape `{other}` (circle | figure-eight | spline)"),
            )),
        }
    }
}

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceConfig {
    /// The environment, the default configuration or a variant.
    pub env: EnvConfig,
    pub shape: PathShape,
    /// Number of demonstrations (episodes), each a different random path of the shape.
    pub episodes: usize,
    /// Control steps per demonstration; the file holds `steps + 1` frames each.
    pub steps: usize,
    /// Seed of the path parameters (episode `k` uses ChaCha8 stream `k`).
    pub seed: u64,
}

impl ReferenceConfig {
    /// 4 demonstrations of 500 steps (10 s on both 2D envs, 20 s on Fetch).
    pub fn new(env: EnvKind, shape: PathShape, seed: u64) -> Self {
        Self {
            env: env.into(),
            shape,
            episodes: 4,
            steps: 500,
            seed,
        }
    }
}

/// Steps per spline segment (a waypoint every 125 steps = 2.5 s on the 2D envs).
const SPLINE_SEGMENT_STEPS: usize = 125;

/// Path sizes as fractions of the configuration box's half-width. They keep the point mass,
/// the slowest system (top speed 0.1 m/s: gear 0.1 N against damping 1 N s/m), inside what the
/// expert can follow without saturating: a loop of radius <= 0.09 m in 10 s needs 0.057 m/s.
const LOOP_AMPLITUDE: std::ops::Range<f64> = 0.15..0.3;
/// Largest waypoint-to-waypoint move of a spline, and the box the waypoints stay in.
const SPLINE_STEP: f64 = 0.25;
const SPLINE_BOX: f64 = 0.6;

/// A smooth path `q(t)` with its derivative, `t` in seconds.
trait Path {
    fn at(&self, t: f64) -> (Vec<f64>, Vec<f64>);
}

/// `q_i(t) = c_i + a_i f_i(w t + phase)` for the closed curves.
struct Periodic {
    centre: Vec<f64>,
    amplitude: Vec<f64>,
    /// Angular frequency (one loop per episode), rad/s.
    omega: f64,
    phase: f64,
    shape: PathShape,
}

impl Path for Periodic {
    fn at(&self, t: f64) -> (Vec<f64>, Vec<f64>) {
        let s = self.omega * t + self.phase;
        // (value, derivative wrt s) of each coordinate's waveform.
        let wave = |i: usize| match (self.shape, i) {
            (PathShape::Circle, 0) | (PathShape::FigureEight, 0) => (s.cos(), -s.sin()),
            (PathShape::Circle, 1) => (s.sin(), s.cos()),
            (PathShape::FigureEight, 1) => ((2.0 * s).sin(), 2.0 * (2.0 * s).cos()),
            // A third dimension (Fetch's height) rises and falls once per loop at half the
            // amplitude: the curve is the same in plan view, on a gently tilted plane.
            _ => (0.5 * s.sin(), 0.5 * s.cos()),
        };
        (0..self.centre.len())
            .map(|i| {
                let (f, df) = wave(i);
                (
                    self.centre[i] + self.amplitude[i] * f,
                    self.amplitude[i] * df * self.omega,
                )
            })
            .unzip()
    }
}

/// Uniform Catmull-Rom spline through `points`, one segment per `segment_s` seconds.
struct CatmullRom {
    points: Vec<Vec<f64>>,
    segment_s: f64,
}

impl Path for CatmullRom {
    fn at(&self, t: f64) -> (Vec<f64>, Vec<f64>) {
        let segments = self.points.len() - 3;
        let x = (t / self.segment_s).clamp(0.0, segments as f64);
        let k = (x.floor() as usize).min(segments - 1);
        let s = x - k as f64;
        let [p0, p1, p2, p3] = [0, 1, 2, 3].map(|j| &self.points[k + j]);
        (0..p1.len())
            .map(|i| {
                let (a, b, c, d) = (p0[i], p1[i], p2[i], p3[i]);
                let c1 = -a + c;
                let c2 = 2.0 * a - 5.0 * b + 4.0 * c - d;
                let c3 = -a + 3.0 * b - 3.0 * c + d;
                let value = b + 0.5 * s * (c1 + s * (c2 + s * c3));
                let slope = 0.5 * (c1 + s * (2.0 * c2 + 3.0 * s * c3));
                (value, slope / self.segment_s)
            })
            .unzip()
    }
}

/// Draws episode `k`'s path inside the inner part of the configuration box, so the expert
/// stays clear of walls and joint limits.
fn random_path(config: &ReferenceConfig, ranges: &[[f64; 2]], dt: f64, k: usize) -> Box<dyn Path> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    rng.set_stream(k as u64);
    let duration = config.steps as f64 * dt;
    let half: Vec<f64> = ranges.iter().map(|[lo, hi]| 0.5 * (hi - lo)).collect();
    let mid: Vec<f64> = ranges.iter().map(|[lo, hi]| 0.5 * (hi + lo)).collect();
    match config.shape {
        PathShape::Circle | PathShape::FigureEight => {
            // One amplitude fraction for every dimension: a true circle on the point mass.
            let fraction = rng.random_range(LOOP_AMPLITUDE);
            let amplitude: Vec<f64> = half.iter().map(|h| fraction * h).collect();
            // The centre moves at most as far as keeps the curve inside 85% of the box.
            let centre = mid
                .iter()
                .zip(&half)
                .zip(&amplitude)
                .map(|((m, h), a)| {
                    let slack = (0.85 * h - a).max(0.0);
                    m + rng.random_range(-1.0..=1.0) * slack
                })
                .collect();
            Box::new(Periodic {
                centre,
                amplitude,
                omega: TAU / duration,
                phase: rng.random_range(0.0..TAU),
                shape: config.shape,
            })
        }
        PathShape::Spline => {
            let segments = config.steps.div_ceil(SPLINE_SEGMENT_STEPS).max(1);
            // A bounded random walk in units of the half-widths; two extra control points set
            // the end tangents.
            let mut walk: Vec<f64> = half
                .iter()
                .map(|_| rng.random_range(-SPLINE_BOX..=SPLINE_BOX))
                .collect();
            let mut points = Vec::with_capacity(segments + 3);
            for _ in 0..segments + 3 {
                points.push(
                    mid.iter()
                        .zip(&half)
                        .zip(&walk)
                        .map(|((m, h), w)| m + h * w)
                        .collect(),
                );
                for w in walk.iter_mut() {
                    *w = (*w + rng.random_range(-SPLINE_STEP..=SPLINE_STEP))
                        .clamp(-SPLINE_BOX, SPLINE_BOX);
                }
            }
            Box::new(CatmullRom {
                points,
                segment_s: SPLINE_SEGMENT_STEPS as f64 * dt,
            })
        }
    }
}

/// Generates the demonstrations; `progress` is called with the number of finished episodes.
pub fn generate_reference(
    config: &ReferenceConfig,
    mut progress: impl FnMut(usize),
) -> Result<Dataset> {
    if config.episodes == 0 {
        return Err(Error::config("episodes", "must be at least 1"));
    }
    if config.steps < 2 {
        return Err(Error::config("steps", "must be at least 2"));
    }
    config.env.validate()?;
    let mut env = config.env.make();
    let (du, dt) = (env.action_dim(), env.control_dt_s());
    let ranges = env.config_ranges();
    let expert = oracle_gains(config.env.kind());
    let steps = config.steps;
    let mut recording = Recording::new(env.as_ref(), config.episodes, steps);
    let mut u = vec![0.0; du];
    for episode in 0..config.episodes {
        let path = random_path(config, &ranges, dt, episode);
        let (q, qd) = path.at(0.0);
        env.set_state(&State { q, qd })?;
        for t in 0..=steps {
            let state = recording.observe(env.as_mut(), episode, t);
            if t == steps {
                break;
            }
            // Aim at where the path is one step ahead: the state this action produces.
            let (q_ref, qd_ref) = path.at((t + 1) as f64 * dt);
            expert.control(&state.q, &state.qd, &q_ref, &qd_ref, &mut u);
            recording.act(episode, t, &u);
            env.step(&u);
        }
        progress(episode + 1);
    }
    let source = format!("demonstration:{}", config.shape.name());
    let mut data = recording.finish(dt, config.seed, source)?;
    data.meta.env_config = (!config.env.is_default()).then(|| config.env.clone());
    Ok(data)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Central difference of a path's value, to check its analytic derivative.
    fn numeric_slope(path: &dyn Path, t: f64) -> Vec<f64> {
        let h = 1e-6;
        let (a, _) = path.at(t + h);
        let (b, _) = path.at(t - h);
        a.iter().zip(&b).map(|(x, y)| (x - y) / (2.0 * h)).collect()
    }

    #[test]
    fn path_derivatives_match_finite_differences() {
        let planar = vec![[-0.3, 0.3], [-0.3, 0.3]];
        let spatial = vec![[-0.3, 0.3], [-0.3, 0.3], [0.4, 0.7]];
        for ranges in [planar, spatial] {
            for shape in [PathShape::Circle, PathShape::FigureEight, PathShape::Spline] {
                let config = ReferenceConfig::new(EnvKind::PointMass, shape, 3);
                let path = random_path(&config, &ranges, 0.02, 1);
                for t in [0.13, 0.77, 1.5, 2.21, 3.9, 6.6, 9.1] {
                    let (q, slope) = path.at(t);
                    assert_eq!(q.len(), ranges.len());
                    for (a, b) in slope.iter().zip(numeric_slope(path.as_ref(), t)) {
                        assert!((a - b).abs() < 1e-5, "{shape:?} t={t}: {a} vs {b}");
                    }
                }
            }
        }
    }

    #[test]
    fn circle_is_a_circle_and_closes() {
        let config = ReferenceConfig::new(EnvKind::PointMass, PathShape::Circle, 0);
        let path = random_path(&config, &[[-0.3, 0.3], [-0.3, 0.3]], 0.02, 0);
        let (start, _) = path.at(0.0);
        let (end, _) = path.at(10.0);
        let (quarter, _) = path.at(2.5);
        assert!((start[0] - end[0]).abs() < 1e-12 && (start[1] - end[1]).abs() < 1e-12);
        // Opposite points are a diameter apart; the quarter point is a radius from the centre.
        let (half, _) = path.at(5.0);
        let centre = [(start[0] + half[0]) / 2.0, (start[1] + half[1]) / 2.0];
        let radius = |p: &[f64]| ((p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2)).sqrt();
        assert!((radius(&start) - radius(&quarter)).abs() < 1e-12);
        assert!(radius(&start) > 0.04 && radius(&start) < 0.1);
    }

    #[test]
    fn paths_stay_inside_the_box() {
        for env in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
            let ranges = env.make().config_ranges();
            for shape in [PathShape::Circle, PathShape::FigureEight, PathShape::Spline] {
                let config = ReferenceConfig::new(env, shape, 7);
                for k in 0..20 {
                    let path = random_path(&config, &ranges, 0.02, k);
                    for step in 0..=config.steps {
                        let (q, _) = path.at(step as f64 * 0.02);
                        for (x, [lo, hi]) in q.iter().zip(&ranges) {
                            assert!(x > lo && x < hi, "{env} {shape:?} path {k}: {x}");
                        }
                    }
                }
            }
        }
    }
}
