//! Top-down rendering of the 2D environments with tiny-skia: a checker floor, anti-aliased shapes.

use tiny_skia::{Color, FillRule, LineCap, Paint, PathBuilder, Pixmap, Rect, Stroke, Transform};

use super::{FRAME_BYTES, FRAME_PX, Frame};

/// dm_control's floor checker colours.
const FLOOR_DARK: [f32; 3] = [0.1, 0.2, 0.3];
const FLOOR_LIGHT: [f32; 3] = [0.2, 0.3, 0.4];

/// A camera looking straight down the world -z axis at the origin, x to the right, y up.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TopDownCamera {
    /// Height of the camera above the floor, metres (dm_control: 0.75).
    pub height_m: f64,
    /// Vertical field of view, degrees (dm_control: 45).
    pub fovy_deg: f64,
    /// Side of one floor checker square, metres.
    pub checker_m: f64,
}

impl Default for TopDownCamera {
    fn default() -> Self {
        Self {
            height_m: 0.75,
            fovy_deg: 45.0,
            checker_m: 0.1,
        }
    }
}

impl TopDownCamera {
    /// Half the side of the square region of the floor that fills the image, metres.
    pub fn half_width_m(&self) -> f64 {
        self.height_m * (self.fovy_deg.to_radians() / 2.0).tan()
    }

    /// Pixels per metre on the floor plane.
    pub fn px_per_m(&self) -> f64 {
        FRAME_PX as f64 / (2.0 * self.half_width_m())
    }

    /// Continuous pixel coordinates (column, row) of a floor point; pixel (c, r) covers
    /// [c, c+1) x [r, r+1), so a point at the image centre maps to (32, 32).
    pub fn project(&self, x_m: f64, y_m: f64) -> (f64, f64) {
        let half = self.half_width_m();
        let scale = self.px_per_m();
        ((x_m + half) * scale, (half - y_m) * scale)
    }
}

/// A shape to draw on the floor, in world metres.
#[derive(Debug, Clone, Copy)]
pub enum Shape {
    /// A filled disc.
    Disc {
        centre: [f64; 2],
        radius: f64,
        rgb: [f32; 3],
    },
    /// A capsule (segment with round ends) of the given radius.
    Capsule {
        from: [f64; 2],
        to: [f64; 2],
        radius: f64,
        rgb: [f32; 3],
    },
}

/// Renders shapes over a cached floor image. Owns its scratch buffers so that rendering a frame
/// allocates nothing.
#[derive(Debug, Clone)]
pub struct Canvas {
    camera: TopDownCamera,
    floor: Pixmap,
    scratch: Pixmap,
}

fn paint(rgb: [f32; 3]) -> Paint<'static> {
    let mut paint = Paint {
        anti_alias: true,
        ..Paint::default()
    };
    paint.set_color(Color::from_rgba(rgb[0], rgb[1], rgb[2], 1.0).unwrap_or(Color::BLACK));
    paint
}

impl Canvas {
    /// Builds the canvas and draws the floor once.
    pub fn new(camera: TopDownCamera) -> Self {
        let side = FRAME_PX as u32;
        let mut floor = Pixmap::new(side, side).expect("64x64 pixmap");
        floor.fill(
            Color::from_rgba(FLOOR_DARK[0], FLOOR_DARK[1], FLOOR_DARK[2], 1.0)
                .unwrap_or(Color::BLACK),
        );
        // Light squares where (i + j) is odd, i, j the checker indices of the floor point.
        let half = camera.half_width_m();
        let n = (half / camera.checker_m).ceil() as i64 + 1;
        let light = paint(FLOOR_LIGHT);
        for i in -n..n {
            for j in -n..n {
                if (i + j).rem_euclid(2) == 1 {
                    let (x0, y1) = camera.project(
                        i as f64 * camera.checker_m,
                        (j + 1) as f64 * camera.checker_m,
                    );
                    let side_px = (camera.checker_m * camera.px_per_m()) as f32;
                    if let Some(rect) = Rect::from_xywh(x0 as f32, y1 as f32, side_px, side_px) {
                        floor.fill_rect(rect, &light, Transform::identity(), None);
                    }
                }
            }
        }
        let scratch = floor.clone();
        Self {
            camera,
            floor,
            scratch,
        }
    }

    /// Draws `shapes` (in order) over the floor and writes the RGB result into `frame`.
    pub fn render(&mut self, shapes: &[Shape], frame: &mut Frame) {
        self.scratch.data_mut().copy_from_slice(self.floor.data());
        let scale = self.camera.px_per_m() as f32;
        for shape in shapes {
            match *shape {
                Shape::Disc {
                    centre,
                    radius,
                    rgb,
                } => {
                    let (cx, cy) = self.camera.project(centre[0], centre[1]);
                    if let Some(path) =
                        PathBuilder::from_circle(cx as f32, cy as f32, radius as f32 * scale)
                    {
                        self.scratch.fill_path(
                            &path,
                            &paint(rgb),
                            FillRule::Winding,
                            Transform::identity(),
                            None,
                        );
                    }
                }
                Shape::Capsule {
                    from,
                    to,
                    radius,
                    rgb,
                } => {
                    let (x0, y0) = self.camera.project(from[0], from[1]);
                    let (x1, y1) = self.camera.project(to[0], to[1]);
                    let mut builder = PathBuilder::new();
                    builder.move_to(x0 as f32, y0 as f32);
                    builder.line_to(x1 as f32, y1 as f32);
                    if let Some(path) = builder.finish() {
                        let stroke = Stroke {
                            width: 2.0 * radius as f32 * scale,
                            line_cap: LineCap::Round,
                            ..Stroke::default()
                        };
                        self.scratch.stroke_path(
                            &path,
                            &paint(rgb),
                            &stroke,
                            Transform::identity(),
                            None,
                        );
                    }
                }
            }
        }
        // Every pixel is opaque, so premultiplied RGBA is plain RGBA: drop alpha.
        for (rgb, rgba) in frame
            .chunks_exact_mut(3)
            .zip(self.scratch.data().chunks_exact(4))
        {
            rgb.copy_from_slice(&rgba[..3]);
        }
        debug_assert_eq!(frame.len(), FRAME_BYTES);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_geometry_matches_dm_control() {
        let camera = TopDownCamera::default();
        // 0.75 * tan(22.5 deg) = 0.310660...
        assert!((camera.half_width_m() - 0.310_660_171_779_821_3).abs() < 1e-12);
        let (c, r) = camera.project(0.0, 0.0);
        assert!((c - 32.0).abs() < 1e-12 && (r - 32.0).abs() < 1e-12);
        // +y is up in the image.
        assert!(camera.project(0.0, 0.1).1 < 32.0);
    }
}
