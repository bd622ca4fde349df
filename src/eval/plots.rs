//! Figures: distance-to-goal curves (log y, mean +- std, like the paper's), latent trajectories,
//! and an episode animation beside its goal image. All written atomically.

use std::path::Path;
use std::sync::Once;

use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font as plotters_register_font};

use super::reach::{EpisodeRecord, MethodSummary};
use crate::error::{Error, Result};
use crate::image_io::RgbImage;

/// Registers the embedded DejaVu Sans as plotters' `sans-serif` (no system fonts needed).
pub fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is a valid TTF compiled into the binary; a failure would only mean no labels.
        let _ = plotters_register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    });
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

fn image_error(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Image {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Draws into an in-memory RGB buffer with `draw`, then writes the PNG atomically.
pub(crate) fn render_png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(
        &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    ) -> std::result::Result<(), String>,
) -> Result<()> {
    register_font();
    let mut buffer = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, size).into_drawing_area();
        root.fill(&WHITE).map_err(|e| image_error(path, e))?;
        draw(&root).map_err(|e| image_error(path, e))?;
        root.present().map_err(|e| image_error(path, e))?;
    }
    RgbImage {
        width: size.0 as usize,
        height: size.1 as usize,
        pixels: buffer,
    }
    .save_png(path, true)
}

/// Distance to goal vs step for each method: mean line and +- std band, log-scale y, with the
/// success threshold dashed.
pub fn save_reach_plot(
    path: &Path,
    title: &str,
    methods: &[MethodSummary],
    threshold: f64,
    unit: &str,
) -> Result<()> {
    render_png(path, (900, 560), |root| {
        let legend =
            |m: &MethodSummary| format!("{} (success {:.0}%)", m.method, 100.0 * m.success_rate);
        let y_desc = format!("distance to goal ({unit})");
        distance_chart(root, title, methods, threshold, &y_desc, legend)
    })
}

/// Per-step distance (mean line, +- std band, log y) of each method on `area`, with
/// `threshold` dashed and each method's legend entry from `legend`.
fn distance_chart(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    title: &str,
    methods: &[MethodSummary],
    threshold: f64,
    y_desc: &str,
    legend: impl Fn(&MethodSummary) -> String,
) -> std::result::Result<(), String> {
    {
        let root = area;
        let steps = methods
            .iter()
            .map(|m| m.per_step_mean.len())
            .max()
            .unwrap_or(1)
            .max(2);
        let positive = |x: f64| x.max(1e-5);
        let hi = methods
            .iter()
            .flat_map(|m| {
                m.per_step_mean
                    .iter()
                    .zip(&m.per_step_std)
                    .map(|(a, b)| a + b)
            })
            .fold(threshold * 2.0, f64::max);
        let lo = methods
            .iter()
            .flat_map(|m| m.per_step_mean.iter().copied())
            .map(positive)
            .fold(threshold / 5.0, f64::min);
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0f64..(steps - 1) as f64, (lo * 0.8..hi * 1.2).log_scale())
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("control step")
            .y_desc(y_desc)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| e.to_string())?;
        for (k, m) in methods.iter().enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            let upper = m
                .per_step_mean
                .iter()
                .zip(&m.per_step_std)
                .enumerate()
                .map(|(t, (a, s))| (t as f64, positive(a + s)));
            let lower = m
                .per_step_mean
                .iter()
                .zip(&m.per_step_std)
                .enumerate()
                .rev()
                .map(|(t, (a, s))| (t as f64, positive(a - s)));
            chart
                .draw_series(std::iter::once(Polygon::new(
                    upper.chain(lower).collect::<Vec<_>>(),
                    color.mix(0.15),
                )))
                .map_err(|e| e.to_string())?;
            let line = m
                .per_step_mean
                .iter()
                .enumerate()
                .map(|(t, a)| (t as f64, positive(*a)));
            let label = legend(m);
            chart
                .draw_series(LineSeries::new(line, color.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label(label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
        }
        chart
            .draw_series(DashedLineSeries::new(
                [(0.0, threshold), ((steps - 1) as f64, threshold)],
                6,
                4,
                BLACK.stroke_width(1),
            ))
            .map_err(|e| e.to_string())?
            .label("success threshold")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| e.to_string())
    }
}

/// Success against wall-clock training seconds (log x), one line with markers per `(label,
/// points)` curve, and the equal training budget (if any) as a dashed vertical line.
pub fn save_learning_plot(
    path: &Path,
    title: &str,
    curves: &[(String, Vec<(f64, f64)>)],
    budget_seconds: Option<f64>,
) -> Result<()> {
    render_png(path, (900, 560), |root| {
        let seconds = curves
            .iter()
            .flat_map(|(_, points)| points.iter().map(|(t, _)| *t))
            .chain(budget_seconds)
            .filter(|t| t.is_finite() && *t > 0.0);
        let (lo, hi) = seconds.fold((f64::INFINITY, 0.0f64), |(lo, hi), t| {
            (lo.min(t), hi.max(t))
        });
        let (lo, hi) = if hi > 0.0 { (lo, hi) } else { (1.0, 10.0) };
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((lo * 0.8..hi * 1.25).log_scale(), 0f64..100f64)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("training time (s, wall clock)")
            .y_desc("goals reached (%)")
            .x_labels(6)
            .x_label_formatter(&|t| format!("{t:.0}"))
            .y_label_formatter(&|p| format!("{p:.0}"))
            .light_line_style(WHITE.mix(0.0))
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| e.to_string())?;
        for (k, (label, points)) in curves.iter().enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            let line: Vec<(f64, f64)> = points
                .iter()
                .filter(|(t, _)| *t > 0.0)
                .map(|(t, success)| (*t, 100.0 * success))
                .collect();
            chart
                .draw_series(LineSeries::new(line.clone(), color.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label(label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            chart
                .draw_series(line.into_iter().map(|p| Circle::new(p, 3, color.filled())))
                .map_err(|e| e.to_string())?;
        }
        if let Some(budget) = budget_seconds.filter(|b| *b > 0.0) {
            chart
                .draw_series(DashedLineSeries::new(
                    [(budget, 0.0), (budget, 100.0)],
                    6,
                    4,
                    BLACK.stroke_width(1),
                ))
                .map_err(|e| e.to_string())?
                .label("equal budget (ProCL's training time)")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| e.to_string())
    })
}

/// A chart over a plane: the latent `(h[0], h[1])` or the configuration `(q[0], q[1])`.
pub(crate) type LatentChart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Builds a latent-plane chart padded 5% around the finite `points` (the unit square when there
/// are none) and draws its axes.
pub(crate) fn latent_plane_chart<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
    title: &str,
    points: impl Iterator<Item = (f64, f64)>,
) -> std::result::Result<LatentChart<'a, 'b>, String> {
    plane_chart(root, title, ("h[0]", "h[1]"), points)
}

/// A 2-D chart with equal spans on both axes, padded 5% around the finite `points`, with the
/// given axis names.
fn plane_chart<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
    title: &str,
    (x_desc, y_desc): (&str, &str),
    points: impl Iterator<Item = (f64, f64)>,
) -> std::result::Result<LatentChart<'a, 'b>, String> {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (x, y) in points.filter(|(x, y)| x.is_finite() && y.is_finite()) {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
    }
    // One span for both axes (the panels are square), so circles stay round and the latent's
    // aspect ratio is the true one.
    let span = (x1 - x0).max(y1 - y0).max(1e-6);
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    (x0, x1, y0, y1) = (
        cx - span / 2.0,
        cx + span / 2.0,
        cy - span / 2.0,
        cy + span / 2.0,
    );
    let pad = 0.05 * span;
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((x0 - pad)..(x1 + pad), (y0 - pad)..(y1 + pad))
        .map_err(|e| e.to_string())?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(|e| e.to_string())?;
    Ok(chart)
}

/// PD trajectories in the latent plane (first two dimensions of `h`): start (circle), path,
/// goal latent (cross), for up to `max_episodes` episodes.
pub fn save_latent_plot(
    path: &Path,
    title: &str,
    episodes: &[EpisodeRecord],
    max_episodes: usize,
) -> Result<()> {
    render_png(path, (640, 640), |root| {
        let points = episodes
            .iter()
            .take(max_episodes)
            .flat_map(|e| e.latents.iter().chain(std::iter::once(&e.goal_latent)))
            .filter(|h| h.len() >= 2)
            .map(|h| (h[0], h[1]));
        let mut chart = latent_plane_chart(root, title, points)?;
        for (k, e) in episodes.iter().take(max_episodes).enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            let line: Vec<(f64, f64)> = e
                .latents
                .iter()
                .filter(|h| h.len() >= 2)
                .map(|h| (h[0], h[1]))
                .collect();
            if let (Some(&start), true) = (line.first(), e.goal_latent.len() >= 2) {
                chart
                    .draw_series(LineSeries::new(line, color.stroke_width(1)))
                    .map_err(|e| e.to_string())?;
                chart
                    .draw_series(std::iter::once(Circle::new(start, 4, color.filled())))
                    .map_err(|e| e.to_string())?;
                let goal = (e.goal_latent[0], e.goal_latent[1]);
                chart
                    .draw_series(std::iter::once(Cross::new(goal, 7, color.stroke_width(3))))
                    .map_err(|e| e.to_string())?;
            }
        }
        Ok(())
    })
}

/// An animated GIF of an episode (every `stride`th frame, upscaled `scale` times) beside the
/// goal image.
pub fn save_episode_gif(
    path: &Path,
    episode: &EpisodeRecord,
    stride: usize,
    scale: usize,
) -> Result<()> {
    let side = crate::envs::FRAME_PX * scale;
    let (width, height) = (2 * side + scale * 2, side);
    let mut bytes = Vec::new();
    {
        let mut encoder = gif::Encoder::new(&mut bytes, width as u16, height as u16, &[])
            .map_err(|e| image_error(path, e))?;
        encoder
            .set_repeat(gif::Repeat::Infinite)
            .map_err(|e| image_error(path, e))?;
        for frame in episode.frames.iter().step_by(stride.max(1)) {
            let mut canvas = RgbImage::new(width, height);
            canvas.pixels.fill(255);
            canvas.blit_scaled(frame, crate::envs::FRAME_PX, 0, 0, scale);
            if let Some(goal) = &episode.goal_frame {
                canvas.blit_scaled(goal, crate::envs::FRAME_PX, side + 2 * scale, 0, scale);
            }
            let mut gif_frame =
                gif::Frame::from_rgb_speed(width as u16, height as u16, &canvas.pixels, 10);
            gif_frame.delay = 4; // hundredths of a second
            encoder
                .write_frame(&gif_frame)
                .map_err(|e| image_error(path, e))?;
        }
    }
    crate::write_atomically(path, true, |w| {
        std::io::Write::write_all(w, &bytes).map_err(|e| Error::io(path, e))
    })
}

/// Tracking figure: left, the reference and achieved paths in the configuration plane
/// `(q[0], q[1])` of up to 4 demonstrations (reference black, latent PD coloured, oracle grey);
/// right, the per-step tracking error of each method (mean +- std, log y).
pub fn save_track_plot(
    path: &Path,
    title: &str,
    references: &[Vec<Vec<f64>>],
    latent_runs: &[EpisodeRecord],
    oracle_runs: &[EpisodeRecord],
    methods: &[super::reach::TrackSummary],
    protocol: &super::reach::ReachConfig,
) -> Result<()> {
    const SHOWN: usize = 4;
    let plane = |q: &Vec<f64>| (q[0], q.get(1).copied().unwrap_or(0.0));
    render_png(path, (1400, 640), |root| {
        let (left, right) = root.split_horizontally(640);
        let three_d = references
            .first()
            .and_then(|r| r.first())
            .is_some_and(|q| q.len() >= 3);
        if three_d {
            draw_paths_3d(&left, title, references, latent_runs, oracle_runs, SHOWN)?;
            return draw_tracking_errors(&right, methods, protocol);
        }
        let points = references
            .iter()
            .take(SHOWN)
            .chain(latent_runs.iter().take(SHOWN).map(|r| &r.configs))
            .flatten()
            .map(plane);
        let mut chart = plane_chart(&left, title, ("q[0]", "q[1]"), points)?;
        let draw = |chart: &mut LatentChart<'_, '_>, line: Vec<(f64, f64)>, style: ShapeStyle| {
            chart
                .draw_series(LineSeries::new(line, style))
                .map(|_| ())
                .map_err(|e| e.to_string())
        };
        for (k, reference) in references.iter().take(SHOWN).enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            draw(
                &mut chart,
                reference.iter().map(plane).collect(),
                BLACK.stroke_width(3),
            )?;
            if let Some(run) = oracle_runs.get(k) {
                let grey = RGBColor(150, 150, 150).stroke_width(1);
                draw(&mut chart, run.configs.iter().map(plane).collect(), grey)?;
            }
            if let Some(run) = latent_runs.get(k) {
                draw(
                    &mut chart,
                    run.configs.iter().map(plane).collect(),
                    color.stroke_width(2),
                )?;
                if let Some(start) = reference.first() {
                    chart
                        .draw_series(std::iter::once(Circle::new(
                            plane(start),
                            5,
                            BLACK.filled(),
                        )))
                        .map_err(|e| e.to_string())?;
                }
            }
        }
        draw_tracking_errors(&right, methods, protocol)
    })
}

/// The per-step tracking error of each method (mean +- std, log y) on `area`.
fn draw_tracking_errors(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    methods: &[super::reach::TrackSummary],
    protocol: &super::reach::ReachConfig,
) -> std::result::Result<(), String> {
    let summaries: Vec<MethodSummary> = methods.iter().map(|m| m.per_step.clone()).collect();
    let legend = |m: &MethodSummary| {
        let mean = methods
            .iter()
            .find(|t| t.per_step.method == m.method)
            .map_or(f64::NAN, |t| t.mean_error);
        format!("{} (mean error {mean:.4})", m.method)
    };
    distance_chart(
        area,
        "tracking error per step (dashed: goal-reaching threshold)",
        &summaries,
        protocol.success_threshold,
        &format!("distance to reference ({})", protocol.distance_unit),
        legend,
    )
}

/// Reference (black) and achieved paths (latent PD coloured, oracle grey) of up to `shown`
/// demonstrations in a 3-D view of the configuration space (Fetch's gripper position).
fn draw_paths_3d(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    title: &str,
    references: &[Vec<Vec<f64>>],
    latent_runs: &[EpisodeRecord],
    oracle_runs: &[EpisodeRecord],
    shown: usize,
) -> std::result::Result<(), String> {
    let point = |q: &Vec<f64>| (q[0], q[1], q[2]);
    let mut bounds = [(f64::MAX, f64::MIN); 3];
    for q in references
        .iter()
        .take(shown)
        .chain(latent_runs.iter().take(shown).map(|r| &r.configs))
        .flatten()
        .filter(|q| q.len() >= 3 && q.iter().all(|x| x.is_finite()))
    {
        for (b, &x) in bounds.iter_mut().zip(q) {
            *b = (b.0.min(x), b.1.max(x));
        }
    }
    // One span for all axes, so the path's shape is not distorted.
    let span = bounds.iter().map(|b| b.1 - b.0).fold(1e-6, f64::max) * 1.1;
    let range = |b: (f64, f64)| {
        let centre = if b.0 <= b.1 { 0.5 * (b.0 + b.1) } else { 0.0 };
        (centre - span / 2.0)..(centre + span / 2.0)
    };
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .build_cartesian_3d(range(bounds[0]), range(bounds[2]), range(bounds[1]))
        .map_err(|e| e.to_string())?;
    chart.with_projection(|mut p| {
        p.yaw = 0.6;
        p.pitch = 0.4;
        p.scale = 0.85;
        p.into_matrix()
    });
    chart
        .configure_axes()
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(|e| e.to_string())?;
    // plotters' 3-D y axis is vertical: plot (q0, q2, q1) so the height q2 points up.
    let upright = |q: &Vec<f64>| {
        let (x, y, z) = point(q);
        (x, z, y)
    };
    for (k, reference) in references.iter().take(shown).enumerate() {
        let mut draw = |line: &[Vec<f64>], style: ShapeStyle| {
            chart
                .draw_series(LineSeries::new(line.iter().map(upright), style))
                .map(|_| ())
                .map_err(|e| e.to_string())
        };
        draw(reference, BLACK.stroke_width(3))?;
        if let Some(run) = oracle_runs.get(k) {
            draw(&run.configs, RGBColor(150, 150, 150).stroke_width(1))?;
        }
        if let Some(run) = latent_runs.get(k) {
            draw(&run.configs, PALETTE[k % PALETTE.len()].stroke_width(2))?;
        }
    }
    Ok(())
}
