//! A small CPU ray caster for the 3D environment: boxes, capsules and upright cylinders,
//! Lambert shading with one shadow-casting directional light, seen through MuJoCo's orbit camera
//! and supersampled for anti-aliasing.
//!
//! Hand-written rather than built on a geometry crate (parry3d would bring nalgebra and parry,
//! several minutes of a 2-core CI build) because the scene needs only three primitive shapes and
//! a fixed camera: the static part (floor, table, robot base) is cast once when the renderer is
//! built and cached per sample, so a frame casts rays only against the ~10 moving arm solids,
//! and only in the pixels their bounding spheres cover. Everything is plain `f64` arithmetic in
//! a fixed order on one thread, so the same scene gives the same bytes every time.

use std::ops::{Add, Mul, Neg, Sub};

use super::{FRAME_PX, Frame};

/// A point or direction in world coordinates, metres.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Vec3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Vec3 {
    /// The origin.
    pub const ZERO: Vec3 = Vec3::new(0.0, 0.0, 0.0);

    /// The vector (x, y, z).
    pub const fn new(x: f64, y: f64, z: f64) -> Self {
        Self { x, y, z }
    }

    /// The vector (a[0], a[1], a[2]).
    pub const fn from_array(a: [f64; 3]) -> Self {
        Self::new(a[0], a[1], a[2])
    }

    /// [x, y, z].
    pub fn to_array(self) -> [f64; 3] {
        [self.x, self.y, self.z]
    }

    /// Scalar product.
    pub fn dot(self, o: Vec3) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    /// Vector product `self x o`.
    pub fn cross(self, o: Vec3) -> Vec3 {
        Vec3::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }

    /// Euclidean length.
    pub fn norm(self) -> f64 {
        self.dot(self).sqrt()
    }

    /// The unit vector along `self` (the zero vector stays zero).
    pub fn normalized(self) -> Vec3 {
        let n = self.norm();
        if n > 0.0 { self * (1.0 / n) } else { self }
    }
}

impl Add for Vec3 {
    type Output = Vec3;
    fn add(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl Sub for Vec3 {
    type Output = Vec3;
    fn sub(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

impl Neg for Vec3 {
    type Output = Vec3;
    fn neg(self) -> Vec3 {
        Vec3::new(-self.x, -self.y, -self.z)
    }
}

impl Mul<f64> for Vec3 {
    type Output = Vec3;
    fn mul(self, s: f64) -> Vec3 {
        Vec3::new(self.x * s, self.y * s, self.z * s)
    }
}

/// A rotation, stored as the rotated frame's unit axes in world coordinates (its columns).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mat3 {
    pub cols: [Vec3; 3],
}

impl Mat3 {
    /// No rotation.
    pub const IDENTITY: Mat3 = Mat3 {
        cols: [
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, 1.0),
        ],
    };

    /// Rotation by `angle` (rad, right-handed) about coordinate axis `axis` (0 = x, 1 = y, 2 = z).
    pub fn about_axis(axis: usize, angle: f64) -> Mat3 {
        let (s, c) = angle.sin_cos();
        let cols = match axis {
            0 => [
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(0.0, c, s),
                Vec3::new(0.0, -s, c),
            ],
            1 => [
                Vec3::new(c, 0.0, -s),
                Vec3::new(0.0, 1.0, 0.0),
                Vec3::new(s, 0.0, c),
            ],
            _ => [
                Vec3::new(c, s, 0.0),
                Vec3::new(-s, c, 0.0),
                Vec3::new(0.0, 0.0, 1.0),
            ],
        };
        Mat3 { cols }
    }

    /// `R v`: a vector given in the rotated frame, in world coordinates.
    pub fn apply(&self, v: Vec3) -> Vec3 {
        self.cols[0] * v.x + self.cols[1] * v.y + self.cols[2] * v.z
    }

    /// `R^T v`: a world vector in the rotated frame's coordinates.
    pub fn apply_inverse(&self, v: Vec3) -> Vec3 {
        Vec3::new(
            self.cols[0].dot(v),
            self.cols[1].dot(v),
            self.cols[2].dot(v),
        )
    }

    /// The composition `self * other` (first `other`, then `self`).
    pub fn compose(&self, other: &Mat3) -> Mat3 {
        Mat3 {
            cols: other.cols.map(|c| self.apply(c)),
        }
    }
}

/// MuJoCo's free camera: it orbits `lookat` at `distance_m`, `azimuth_deg` measured about +z
/// from +x, `elevation_deg` negative when looking down. The observation is the centre
/// `FRAME_PX` x `FRAME_PX` crop of a `full_render_px`-square render with vertical field of view
/// `fovy_deg`, which is rendered directly as a 64x64 image with the cropped field of view.
/// A variant file's camera table names only the fields it changes (the rest: FetchReach's).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OrbitCamera {
    /// Distance from the look-at point, m.
    pub distance_m: f64,
    /// Direction of view about +z, measured from +x, degrees.
    pub azimuth_deg: f64,
    /// Direction of view above the horizontal, degrees (negative: looking down).
    pub elevation_deg: f64,
    /// The point at the image centre, world metres.
    pub lookat_m: [f64; 3],
    /// Vertical field of view of the full render, degrees.
    pub fovy_deg: f64,
    /// Side of the render the observation is cropped from, pixels (>= 64).
    pub full_render_px: usize,
}

impl Default for OrbitCamera {
    /// FetchReach's camera.
    fn default() -> Self {
        Self {
            distance_m: 2.5,
            azimuth_deg: 132.0,
            elevation_deg: -14.0,
            lookat_m: [1.3, 0.75, 0.55],
            fovy_deg: 45.0,
            full_render_px: 128,
        }
    }
}

impl OrbitCamera {
    /// Position, unit axes and the crop's half field of view (as a tangent).
    pub(crate) fn basis(&self) -> CameraBasis {
        let (sa, ca) = self.azimuth_deg.to_radians().sin_cos();
        let (se, ce) = self.elevation_deg.to_radians().sin_cos();
        // mjv_updateCamera: forward and up from azimuth and elevation, right = forward x up.
        let forward = Vec3::new(ce * ca, ce * sa, se);
        let up = Vec3::new(-se * ca, -se * sa, ce);
        let right = forward.cross(up);
        let eye = Vec3::from_array(self.lookat_m) - forward * self.distance_m;
        let crop = FRAME_PX as f64 / self.full_render_px.max(1) as f64;
        let tan_half = (self.fovy_deg.to_radians() / 2.0).tan() * crop;
        CameraBasis {
            eye,
            forward,
            right,
            up,
            tan_half,
        }
    }

    /// Camera position in the world, metres.
    pub fn eye(&self) -> Vec3 {
        self.basis().eye
    }

    /// Continuous pixel coordinates (column, row) of a world point in the 64x64 observation;
    /// pixel (c, r) covers [c, c+1) x [r, r+1), row 0 at the top. `None` behind the camera.
    pub fn project(&self, p: Vec3) -> Option<(f64, f64)> {
        self.basis().project(p)
    }
}

/// The camera's frame, computed once per renderer.
#[derive(Debug, Clone, Copy)]
pub(crate) struct CameraBasis {
    eye: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    /// tan of half the observation's field of view.
    tan_half: f64,
}

impl CameraBasis {
    /// Pixels per unit of (lateral offset / depth).
    fn focal_px(&self) -> f64 {
        FRAME_PX as f64 / 2.0 / self.tan_half
    }

    fn project(&self, p: Vec3) -> Option<(f64, f64)> {
        let d = p - self.eye;
        let depth = d.dot(self.forward);
        if depth <= 1e-9 {
            return None;
        }
        let (f, c) = (self.focal_px(), FRAME_PX as f64 / 2.0);
        Some((
            c + f * d.dot(self.right) / depth,
            c - f * d.dot(self.up) / depth,
        ))
    }

    /// Unit direction of the ray through continuous pixel coordinates (x, y).
    fn ray(&self, x: f64, y: f64) -> Vec3 {
        let f = self.focal_px();
        let c = FRAME_PX as f64 / 2.0;
        (self.forward + self.right * ((x - c) / f) - self.up * ((y - c) / f)).normalized()
    }

    /// Conservative pixel bounding box `[col0, col1] x [row0, row1]` (inclusive, clamped to the
    /// image) of a sphere; `None` when it is entirely off screen.
    fn sphere_bbox(&self, centre: Vec3, radius: f64) -> Option<[usize; 4]> {
        let last = FRAME_PX as f64 - 1.0;
        let d = centre - self.eye;
        let depth = d.dot(self.forward);
        if depth - radius <= 1e-3 {
            // Reaches behind the near plane: test every pixel.
            return Some([0, FRAME_PX - 1, 0, FRAME_PX - 1]);
        }
        let (x, y) = self.project(centre)?;
        // A point C + e, |e| <= r, projects within f r (1 + |C_lateral| / depth) / (depth - r) of
        // C's projection along each image axis.
        let f = self.focal_px();
        let rx = f * radius * (1.0 + d.dot(self.right).abs() / depth) / (depth - radius);
        let ry = f * radius * (1.0 + d.dot(self.up).abs() / depth) / (depth - radius);
        let (x0, x1, y0, y1) = (x - rx, x + rx, y - ry, y + ry);
        if x1 < 0.0 || y1 < 0.0 || x0 > last + 1.0 || y0 > last + 1.0 {
            return None;
        }
        let clamp = |v: f64| v.floor().clamp(0.0, last) as usize;
        Some([clamp(x0), clamp(x1), clamp(y0), clamp(y1)])
    }
}

/// One directional light that casts shadows, an ambient term and a shadowless headlight. A
/// variant file's lighting table names only the fields it changes (the rest: Fetch-3D's).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Lighting {
    /// Direction from the scene towards the light (need not be unit length).
    pub to_light: [f64; 3],
    /// Light reaching every surface.
    pub ambient: f64,
    /// Strength of the directional light (Lambert, times 0 in shadow).
    pub diffuse: f64,
    /// Strength of a light at the camera (Lambert on the viewing direction, never shadowed),
    /// like MuJoCo's headlight: it keeps faces turned away from the sun from going flat.
    pub headlight: f64,
}

impl Default for Lighting {
    /// Fetch-3D's sun: from above, tilted slightly towards the camera side so the table's
    /// front and side faces differ; shadows fall almost straight down, where the camera sees
    /// them below the gripper.
    fn default() -> Self {
        Self {
            to_light: [0.2, -0.1, 1.0],
            ambient: 0.35,
            diffuse: 0.6,
            headlight: 0.2,
        }
    }
}

/// The geometry of one solid, world coordinates, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Solid {
    /// The points within `radius` of the segment `a`-`b`.
    Capsule { a: Vec3, b: Vec3, radius: f64 },
    /// A box with unit axes `axes.cols` and half-extents `half` along them.
    Cuboid {
        centre: Vec3,
        axes: Mat3,
        half: Vec3,
    },
    /// A capped cylinder with a vertical (world z) axis, standing on `base`.
    Cylinder {
        base: Vec3,
        height: f64,
        radius: f64,
    },
}

/// Most moving objects one frame can hold.
pub(crate) const MAX_MOVING: usize = 64;

/// Rays start this far along their direction before they can hit anything (metres), so a
/// shadow ray does not hit the surface it leaves.
const T_MIN: f64 = 1e-7;

/// A ray hit: distance along the (unit) ray and the outward unit normal there.
#[derive(Debug, Clone, Copy)]
struct Hit {
    t: f64,
    normal: Vec3,
}

impl Solid {
    /// An axis-aligned box.
    pub(crate) fn aabb(centre: Vec3, half: Vec3) -> Solid {
        Solid::Cuboid {
            centre,
            axes: Mat3::IDENTITY,
            half,
        }
    }

    /// A sphere enclosing the solid: (centre, radius).
    fn bounding_sphere(&self) -> (Vec3, f64) {
        match *self {
            Solid::Capsule { a, b, radius } => ((a + b) * 0.5, (b - a).norm() * 0.5 + radius),
            Solid::Cuboid { centre, half, .. } => (centre, half.norm()),
            Solid::Cylinder {
                base,
                height,
                radius,
            } => (
                base + Vec3::new(0.0, 0.0, height * 0.5),
                (radius * radius + height * height * 0.25).sqrt(),
            ),
        }
    }

    /// The nearest entry of the unit ray `o + t d` into the solid with `T_MIN < t < t_max`.
    /// A ray starting inside a solid does not hit it: every point the camera sees, and so every
    /// shadow ray's origin, is outside all solids.
    fn intersect(&self, o: Vec3, d: Vec3, t_max: f64) -> Option<Hit> {
        let hit = match *self {
            Solid::Capsule { a, b, radius } => capsule_hit(o, d, a, b, radius),
            Solid::Cuboid { centre, axes, half } => {
                let local = cuboid_hit(axes.apply_inverse(o - centre), axes.apply_inverse(d), half);
                local.map(|h| Hit {
                    t: h.t,
                    normal: axes.apply(h.normal),
                })
            }
            Solid::Cylinder {
                base,
                height,
                radius,
            } => cylinder_hit(o - base, d, height, radius),
        }?;
        (hit.t > T_MIN && hit.t < t_max).then_some(hit)
    }
}

/// Sphere of `radius` at the origin, ray from `oc` (a capsule's cap).
fn sphere_hit(oc: Vec3, d: Vec3, radius: f64) -> Option<Hit> {
    let b = oc.dot(d);
    let h = b * b - (oc.dot(oc) - radius * radius);
    if h < 0.0 {
        return None;
    }
    let t = -b - h.sqrt();
    Some(Hit {
        t,
        normal: (oc + d * t) * (1.0 / radius),
    })
}

/// Capsule `a`-`b` (after Inigo Quilez's capsule intersector): the cylinder body, else the
/// cap sphere on the side the ray meets.
fn capsule_hit(o: Vec3, d: Vec3, a: Vec3, b: Vec3, radius: f64) -> Option<Hit> {
    let ba = b - a;
    let oa = o - a;
    let baba = ba.dot(ba);
    let bard = ba.dot(d);
    let baoa = ba.dot(oa);
    let rdoa = d.dot(oa);
    let oaoa = oa.dot(oa);
    let qa = baba - bard * bard;
    let qb = baba * rdoa - baoa * bard;
    let qc = baba * oaoa - baoa * baoa - radius * radius * baba;
    let h = qb * qb - qa * qc;
    if h < 0.0 {
        return None;
    }
    if qa > 1e-12 {
        let t = (-qb - h.sqrt()) / qa;
        let y = baoa + t * bard;
        if y > 0.0 && y < baba {
            let normal = (oa + d * t - ba * (y / baba)) * (1.0 / radius);
            return Some(Hit { t, normal });
        }
        let cap = if y <= 0.0 { oa } else { o - b };
        return sphere_hit(cap, d, radius);
    }
    // The ray runs along the axis: it meets the cap it travels towards first.
    let cap = if bard > 0.0 { oa } else { o - b };
    sphere_hit(cap, d, radius)
}

/// Axis-aligned box of half-extents `half` at the origin (slab method).
fn cuboid_hit(o: Vec3, d: Vec3, half: Vec3) -> Option<Hit> {
    let (o, d, h) = (o.to_array(), d.to_array(), half.to_array());
    let (mut t_near, mut t_far, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 0);
    for i in 0..3 {
        if d[i].abs() < 1e-300 {
            if o[i].abs() > h[i] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d[i];
        let (mut t0, mut t1) = ((-h[i] - o[i]) * inv, (h[i] - o[i]) * inv);
        if t0 > t1 {
            std::mem::swap(&mut t0, &mut t1);
        }
        if t0 > t_near {
            t_near = t0;
            axis = i;
        }
        t_far = t_far.min(t1);
    }
    if t_near > t_far {
        return None;
    }
    let mut normal = [0.0; 3];
    normal[axis] = if d[axis] > 0.0 { -1.0 } else { 1.0 };
    Some(Hit {
        t: t_near,
        normal: Vec3::from_array(normal),
    })
}

/// Vertical capped cylinder standing on the origin.
fn cylinder_hit(o: Vec3, d: Vec3, height: f64, radius: f64) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    let mut take = |t: f64, normal: Vec3| {
        if t > T_MIN && best.is_none_or(|b| t < b.t) {
            best = Some(Hit { t, normal });
        }
    };
    let a = d.x * d.x + d.y * d.y;
    if a > 1e-300 {
        let b = o.x * d.x + o.y * d.y;
        let c = o.x * o.x + o.y * o.y - radius * radius;
        let h = b * b - a * c;
        if h >= 0.0 {
            let t = (-b - h.sqrt()) / a;
            let z = o.z + t * d.z;
            if (0.0..=height).contains(&z) {
                let p = o + d * t;
                take(t, Vec3::new(p.x / radius, p.y / radius, 0.0));
            }
        }
    }
    if d.z.abs() > 1e-300 {
        for (z, nz) in [(height, 1.0), (0.0, -1.0)] {
            // A cap faces the ray only when the ray travels against its normal.
            if d.z * nz < 0.0 {
                let t = (z - o.z) / d.z;
                let p = o + d * t;
                if p.x * p.x + p.y * p.y <= radius * radius {
                    take(t, Vec3::new(0.0, 0.0, nz));
                }
            }
        }
    }
    best
}

/// A solid with its colour and a name (what [`RayCaster::pick`] reports).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Object {
    pub solid: Solid,
    /// Albedo, RGB in [0, 1].
    pub rgb: [f32; 3],
    pub label: &'static str,
}

/// A moving object prepared for one frame: where on screen and in the light's view it can be.
#[derive(Debug, Clone, Copy)]
struct Prepared {
    /// Pixel bounding box [col0, col1, row0, row1], or none when off screen.
    bbox: Option<[usize; 4]>,
    /// Bounding circle in light space (coordinates across the light direction) and radius^2.
    light_uv: [f64; 2],
    light_r2: f64,
}

/// What a camera sample sees of the static scene, computed once.
#[derive(Debug, Clone, Copy)]
struct StaticSample {
    dir: Vec3,
    /// Distance to the static surface (infinity: sky).
    t: f64,
    point: Vec3,
    light_uv: [f64; 2],
    /// Colour when the light reaches the point, and when a moving object shadows it.
    lit: [f32; 3],
    shadowed: [f32; 3],
    /// Whether a moving object could change the colour (the point faces the light and no
    /// static object shadows it).
    shadow_test: bool,
}

/// Renders a fixed static scene plus per-frame moving objects into 64x64 frames.
#[derive(Debug, Clone)]
pub(crate) struct RayCaster {
    basis: CameraBasis,
    lighting: Lighting,
    /// Unit vector to the light and two unit vectors across it.
    to_light: Vec3,
    light_u: Vec3,
    light_v: Vec3,
    statics: Vec<Object>,
    sky: [f32; 3],
    samples_per_axis: usize,
    /// `FRAME_PX^2` pixels, each `samples_per_axis^2` samples, pixel-major.
    cache: Vec<StaticSample>,
    prepared: Vec<Prepared>,
}

/// A ray's first hit, for tests and tools.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Picked {
    /// The object's label (Fetch: `gripper`, `arm`, `table`, `floor`, `robot`).
    pub label: &'static str,
    /// Where the ray hits it, world metres.
    pub point: Vec3,
}

impl RayCaster {
    /// Builds the renderer and casts the static scene once. `samples_per_axis` (>= 1) squared
    /// rays per pixel are averaged (anti-aliasing); `sky` is the colour where nothing is hit.
    pub(crate) fn new(
        camera: &OrbitCamera,
        lighting: Lighting,
        statics: Vec<Object>,
        sky: [f32; 3],
        samples_per_axis: usize,
    ) -> Self {
        let to_light = Vec3::from_array(lighting.to_light).normalized();
        // Any unit vector not parallel to the light, then two across it.
        let helper = if to_light.z.abs() < 0.9 {
            Vec3::new(0.0, 0.0, 1.0)
        } else {
            Vec3::new(1.0, 0.0, 0.0)
        };
        let light_u = to_light.cross(helper).normalized();
        let light_v = to_light.cross(light_u);
        let mut caster = Self {
            basis: camera.basis(),
            lighting,
            to_light,
            light_u,
            light_v,
            statics,
            sky,
            samples_per_axis: samples_per_axis.max(1),
            cache: vec![],
            prepared: vec![],
        };
        caster.cache = caster.cast_static();
        caster
    }

    /// Sample positions inside pixel (col, row), in continuous pixel coordinates.
    fn sample_positions(&self, col: usize, row: usize) -> impl Iterator<Item = (f64, f64)> {
        let s = self.samples_per_axis;
        (0..s * s).map(move |k| {
            let fx = ((k % s) as f64 + 0.5) / s as f64;
            let fy = ((k / s) as f64 + 0.5) / s as f64;
            (col as f64 + fx, row as f64 + fy)
        })
    }

    fn cast_static(&self) -> Vec<StaticSample> {
        let mut cache = Vec::with_capacity(FRAME_PX * FRAME_PX * self.samples_per_axis.pow(2));
        for row in 0..FRAME_PX {
            for col in 0..FRAME_PX {
                for (x, y) in self.sample_positions(col, row) {
                    let dir = self.basis.ray(x, y);
                    cache.push(self.static_sample(dir));
                }
            }
        }
        cache
    }

    fn static_sample(&self, dir: Vec3) -> StaticSample {
        let eye = self.basis.eye;
        let nearest = nearest_hit(&self.statics, eye, dir, f64::INFINITY);
        let Some((index, hit)) = nearest else {
            return StaticSample {
                dir,
                t: f64::INFINITY,
                point: eye,
                light_uv: [0.0; 2],
                lit: self.sky,
                shadowed: self.sky,
                shadow_test: false,
            };
        };
        let point = eye + dir * hit.t;
        let rgb = self.statics[index].rgb;
        let faces_light = hit.normal.dot(self.to_light) > 0.0;
        let in_static_shadow = faces_light && self.occluded(&self.statics, point, hit.normal);
        let shadowed = self.shade(rgb, hit.normal, dir, false);
        let lit = if faces_light && !in_static_shadow {
            self.shade(rgb, hit.normal, dir, true)
        } else {
            shadowed
        };
        StaticSample {
            dir,
            t: hit.t,
            point,
            light_uv: self.light_uv(point),
            lit,
            shadowed,
            shadow_test: faces_light && !in_static_shadow,
        }
    }

    fn light_uv(&self, p: Vec3) -> [f64; 2] {
        [p.dot(self.light_u), p.dot(self.light_v)]
    }

    /// Lambert shading of albedo `rgb` with normal `n`, seen along `dir`.
    fn shade(&self, rgb: [f32; 3], n: Vec3, dir: Vec3, sunlit: bool) -> [f32; 3] {
        let l = &self.lighting;
        let mut k = l.ambient + l.headlight * (-n.dot(dir)).max(0.0);
        if sunlit {
            k += l.diffuse * n.dot(self.to_light).max(0.0);
        }
        rgb.map(|c| (c as f64 * k) as f32)
    }

    /// Whether any of `objects` blocks the light from `point` (on a surface with normal `n`).
    fn occluded(&self, objects: &[Object], point: Vec3, n: Vec3) -> bool {
        let origin = point + n * 1e-6;
        objects.iter().any(|o| {
            o.solid
                .intersect(origin, self.to_light, f64::INFINITY)
                .is_some()
        })
    }

    /// Whether a moving object blocks the light from `point`, testing only those whose
    /// light-space bounding circle covers it.
    fn occluded_by_moving(&self, moving: &[Object], point: Vec3, n: Vec3, uv: [f64; 2]) -> bool {
        let origin = point + n * 1e-6;
        moving.iter().zip(&self.prepared).any(|(o, p)| {
            let (du, dv) = (uv[0] - p.light_uv[0], uv[1] - p.light_uv[1]);
            du * du + dv * dv < p.light_r2
                && o.solid
                    .intersect(origin, self.to_light, f64::INFINITY)
                    .is_some()
        })
    }

    fn prepare(&mut self, moving: &[Object]) {
        self.prepared.clear();
        for o in moving {
            let (centre, radius) = o.solid.bounding_sphere();
            self.prepared.push(Prepared {
                bbox: self.basis.sphere_bbox(centre, radius),
                light_uv: self.light_uv(centre),
                light_r2: radius * radius,
            });
        }
    }

    /// Renders the static scene plus `moving` into `frame`. The moving objects of a pixel are
    /// kept in a 64-bit set, so at most [`MAX_MOVING`] of them (Fetch has 10).
    pub(crate) fn render(&mut self, moving: &[Object], frame: &mut Frame) {
        debug_assert!(moving.len() <= MAX_MOVING);
        let moving = &moving[..moving.len().min(MAX_MOVING)];
        self.prepare(moving);
        let per_pixel = self.samples_per_axis * self.samples_per_axis;
        let eye = self.basis.eye;
        for row in 0..FRAME_PX {
            // Moving objects whose boxes cover this row, as a bit set.
            let row_mask = self
                .prepared
                .iter()
                .enumerate()
                .fold(0u64, |m, (i, p)| match p.bbox {
                    Some([_, _, r0, r1]) if (r0..=r1).contains(&row) => m | 1 << i,
                    _ => m,
                });
            for col in 0..FRAME_PX {
                let pixel = row * FRAME_PX + col;
                let mut mask = 0u64;
                let mut bits = row_mask;
                while bits != 0 {
                    let i = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    if let Some([c0, c1, _, _]) = self.prepared[i].bbox
                        && (c0..=c1).contains(&col)
                    {
                        mask |= 1 << i;
                    }
                }
                let mut sum = [0f32; 3];
                for s in &self.cache[pixel * per_pixel..(pixel + 1) * per_pixel] {
                    let rgb = self.sample_colour(moving, mask, s, eye);
                    for c in 0..3 {
                        sum[c] += rgb[c];
                    }
                }
                let out = &mut frame[pixel * 3..pixel * 3 + 3];
                for c in 0..3 {
                    let v = sum[c] / per_pixel as f32;
                    out[c] = (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
                }
            }
        }
    }

    /// The colour of one camera sample given the moving objects in `mask`.
    fn sample_colour(&self, moving: &[Object], mask: u64, s: &StaticSample, eye: Vec3) -> [f32; 3] {
        let mut nearest: Option<(usize, Hit)> = None;
        let mut t_max = s.t;
        let mut bits = mask;
        while bits != 0 {
            let i = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            if let Some(hit) = moving[i].solid.intersect(eye, s.dir, t_max) {
                t_max = hit.t;
                nearest = Some((i, hit));
            }
        }
        match nearest {
            Some((i, hit)) => {
                let point = eye + s.dir * hit.t;
                let sunlit = hit.normal.dot(self.to_light) > 0.0
                    && !self.occluded(&self.statics, point, hit.normal)
                    && !self.occluded_by_moving(moving, point, hit.normal, self.light_uv(point));
                self.shade(moving[i].rgb, hit.normal, s.dir, sunlit)
            }
            None if s.shadow_test
                && self.occluded_by_moving(moving, s.point, Vec3::ZERO, s.light_uv) =>
            {
                s.shadowed
            }
            None => s.lit,
        }
    }

    /// The first object the ray through continuous pixel coordinates (x, y) hits, static or
    /// moving, with the hit point; `None` for sky.
    pub(crate) fn pick(&self, moving: &[Object], x: f64, y: f64) -> Option<Picked> {
        let dir = self.basis.ray(x, y);
        let eye = self.basis.eye;
        let fixed = nearest_hit(&self.statics, eye, dir, f64::INFINITY);
        let t_static = fixed.map_or(f64::INFINITY, |(_, h)| h.t);
        let (object, hit) = match nearest_hit(moving, eye, dir, t_static) {
            Some((i, h)) => (&moving[i], h),
            None => {
                let (i, h) = fixed?;
                (&self.statics[i], h)
            }
        };
        Some(Picked {
            label: object.label,
            point: eye + dir * hit.t,
        })
    }
}

/// The nearest hit among `objects` closer than `t_max`: (index, hit).
fn nearest_hit(objects: &[Object], o: Vec3, d: Vec3, t_max: f64) -> Option<(usize, Hit)> {
    let mut best = None;
    let mut t_max = t_max;
    for (i, object) in objects.iter().enumerate() {
        if let Some(hit) = object.solid.intersect(o, d, t_max) {
            t_max = hit.t;
            best = Some((i, hit));
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: Vec3, b: Vec3, tol: f64) -> bool {
        (a - b).norm() < tol
    }

    #[test]
    fn primitives_hit_where_expected() {
        let o = Vec3::new(0.0, 0.0, 5.0);
        let down = Vec3::new(0.0, 0.0, -1.0);
        // A zero-length capsule is a sphere.
        let sphere = Solid::Capsule {
            a: Vec3::ZERO,
            b: Vec3::ZERO,
            radius: 1.0,
        };
        let h = sphere.intersect(o, down, f64::INFINITY).unwrap();
        assert!((h.t - 4.0).abs() < 1e-12 && close(h.normal, Vec3::new(0.0, 0.0, 1.0), 1e-12));
        // A horizontal capsule seen from above: hit on top of the body, and on the end cap.
        let capsule = Solid::Capsule {
            a: Vec3::new(-1.0, 0.0, 0.0),
            b: Vec3::new(1.0, 0.0, 0.0),
            radius: 0.5,
        };
        let h = capsule.intersect(o, down, f64::INFINITY).unwrap();
        assert!((h.t - 4.5).abs() < 1e-12);
        let h = capsule
            .intersect(Vec3::new(1.3, 0.0, 5.0), down, f64::INFINITY)
            .unwrap();
        let expected_z = (0.25f64 - 0.09).sqrt();
        assert!((h.t - (5.0 - expected_z)).abs() < 1e-12);
        // Along the axis: the near cap.
        let h = capsule
            .intersect(Vec3::new(5.0, 0.0, 0.0), Vec3::new(-1.0, 0.0, 0.0), 100.0)
            .unwrap();
        assert!((h.t - 3.5).abs() < 1e-12 && close(h.normal, Vec3::new(1.0, 0.0, 0.0), 1e-12));
        // A box rotated 90 degrees about z swaps its x and y extents.
        let cuboid = Solid::Cuboid {
            centre: Vec3::ZERO,
            axes: Mat3::about_axis(2, std::f64::consts::FRAC_PI_2),
            half: Vec3::new(2.0, 0.5, 0.25),
        };
        assert!(
            cuboid
                .intersect(Vec3::new(1.0, 0.0, 5.0), down, 100.0)
                .is_none()
        );
        let h = cuboid
            .intersect(Vec3::new(0.0, 1.5, 5.0), down, 100.0)
            .unwrap();
        assert!((h.t - 4.75).abs() < 1e-12 && close(h.normal, Vec3::new(0.0, 0.0, 1.0), 1e-12));
        let cylinder = Solid::Cylinder {
            base: Vec3::ZERO,
            height: 2.0,
            radius: 1.0,
        };
        let h = cylinder.intersect(o, down, 100.0).unwrap();
        assert!((h.t - 3.0).abs() < 1e-12);
        let h = cylinder
            .intersect(Vec3::new(5.0, 0.0, 1.0), Vec3::new(-1.0, 0.0, 0.0), 100.0)
            .unwrap();
        assert!((h.t - 4.0).abs() < 1e-12 && close(h.normal, Vec3::new(1.0, 0.0, 0.0), 1e-12));
        // t_max and T_MIN bound the hits.
        assert!(sphere.intersect(o, down, 3.9).is_none());
        assert!(sphere.intersect(o, -down, f64::INFINITY).is_none());
    }

    #[test]
    fn camera_projection_inverts_rays() {
        let camera = OrbitCamera::default();
        let basis = camera.basis();
        // The look-at point is the image centre.
        let (c, r) = camera.project(Vec3::from_array(camera.lookat_m)).unwrap();
        assert!((c - 32.0).abs() < 1e-9 && (r - 32.0).abs() < 1e-9);
        for (x, y) in [(0.5, 0.5), (10.25, 50.0), (63.9, 12.0)] {
            let p = basis.eye + basis.ray(x, y) * 1.7;
            let (c, r) = camera.project(p).unwrap();
            assert!((c - x).abs() < 1e-9 && (r - y).abs() < 1e-9);
        }
        // Higher points are higher in the image (smaller rows).
        let low = camera.project(Vec3::new(1.3, 0.75, 0.4)).unwrap();
        let high = camera.project(Vec3::new(1.3, 0.75, 0.7)).unwrap();
        assert!(high.1 < low.1);
    }

    #[test]
    fn bounding_boxes_contain_the_projection() {
        let camera = OrbitCamera::default();
        let basis = camera.basis();
        let centre = Vec3::new(1.2, 0.9, 0.6);
        let radius = 0.1;
        let [c0, c1, r0, r1] = basis.sphere_bbox(centre, radius).unwrap();
        for k in 0..200 {
            let a = k as f64 * 0.7;
            let b = k as f64 * 1.3;
            let e = Vec3::new(a.cos() * b.sin(), a.sin() * b.sin(), b.cos()) * radius;
            if let Some((c, r)) = camera.project(centre + e) {
                let (c, r) = (c.floor() as usize, r.floor() as usize);
                assert!((c0..=c1).contains(&c) && (r0..=r1).contains(&r));
            }
        }
    }

    /// A red ball hidden behind a box must not show; moved beside it, it shows and casts a
    /// shadow on the floor.
    #[test]
    fn depth_test_and_shadows() {
        let camera = OrbitCamera {
            distance_m: 3.0,
            azimuth_deg: 0.0,
            elevation_deg: -30.0,
            lookat_m: [0.0, 0.0, 0.0],
            fovy_deg: 45.0,
            full_render_px: 64,
        };
        let lighting = Lighting {
            to_light: [0.0, 0.0, 1.0],
            ambient: 0.3,
            diffuse: 0.7,
            headlight: 0.0,
        };
        let floor = Object {
            solid: Solid::aabb(Vec3::new(0.0, 0.0, -0.05), Vec3::new(5.0, 5.0, 0.05)),
            rgb: [1.0, 1.0, 1.0],
            label: "floor",
        };
        // The camera is at -x, above; the wall stands between it and the origin.
        let wall = Object {
            solid: Solid::aabb(Vec3::new(-0.6, 0.0, 0.5), Vec3::new(0.05, 0.3, 0.5)),
            rgb: [0.0, 0.0, 1.0],
            label: "wall",
        };
        let mut caster = RayCaster::new(&camera, lighting, vec![floor, wall], [0.0; 3], 1);
        let ball = |centre: Vec3| Object {
            solid: Solid::Capsule {
                a: centre,
                b: centre,
                radius: 0.1,
            },
            rgb: [1.0, 0.0, 0.0],
            label: "ball",
        };
        let red = |f: &Frame| {
            f.chunks_exact(3)
                .filter(|p| p[0] > 100 && p[2] < 50)
                .count()
        };
        let mut frame = [0u8; crate::envs::FRAME_BYTES];
        caster.render(&[ball(Vec3::new(0.0, 0.0, 0.3))], &mut frame);
        assert_eq!(red(&frame), 0, "the ball behind the wall shows through");
        let beside = Vec3::new(0.0, 0.7, 0.3);
        caster.render(&[ball(beside)], &mut frame);
        assert!(red(&frame) > 3);
        let (c, r) = camera.project(beside).unwrap();
        let picked = caster.pick(&[ball(beside)], c, r).unwrap();
        assert_eq!(picked.label, "ball");
        // Its shadow falls straight down on the floor.
        let (c, r) = camera.project(Vec3::new(0.0, 0.7, 0.0)).unwrap();
        let picked = caster.pick(&[ball(beside)], c, r).unwrap();
        assert_eq!(picked.label, "floor");
        let px = (r as usize * FRAME_PX + c as usize) * 3;
        assert!(
            frame[px] < 100,
            "floor under the ball is lit: {}",
            frame[px]
        );
        caster.render(&[], &mut frame);
        assert!(
            frame[px] > 200,
            "floor without the ball is dark: {}",
            frame[px]
        );
    }
}
