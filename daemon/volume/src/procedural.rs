//! Built-in volumes. All are signed fields, positive inside the object, sampled on an N^3-ish grid
//! with spacing 1 and origin 0 (world units = voxels), with a natural iso value.
//!
//! The object is `{f >= iso}` (DESIGN.md "Isosurface"). Every volume here except Marschner-Lobb is
//! a signed distance (or a min/max combination of signed distances; for the gyroid sheet only
//! roughly) in voxel units with iso 0; Marschner-Lobb is the classic signal in [0, 1] with iso 0.5.
//!
//! | name                | default dims    | iso | what                                              |
//! |---------------------|-----------------|-----|---------------------------------------------------|
//! | `sphere`            | 64^3            | 0   | sphere, r = 0.35 (n-1), at the box centre         |
//! | `sphere-over-plane` | 64^3            | 0   | floating sphere over a half-space; exact AO known |
//! | `torus`             | 64^3            | 0   | torus R = 0.3 (n-1), r = 0.12 (n-1), tilted 20°   |
//! | `marschner-lobb`    | 41^3            | 0.5 | Marschner & Lobb (1994) test signal               |
//! | `gyroid`            | 64^3            | 0   | sheet gyroid, 3 periods, clipped by a ball        |
//! | `engine`            | 256x256x118     | 0   | engine-like machined block: bores, fins, flange   |
//!
//! `size` is the largest dimension; all are cubes except the engine, whose z keeps the 256:118
//! aspect (`nz = round(size * 118 / 256)`, at least 2).

use crate::Volume;
use glam::DVec3;
use std::f64::consts::PI;

/// The sizes a procedural volume may be asked for (`procedural:NAME:N`): its largest dimension.
pub const SIZES: std::ops::RangeInclusive<usize> = 2..=1024;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Procedural {
    Sphere,
    SphereOverPlane,
    Torus,
    MarschnerLobb,
    Gyroid,
    Engine,
}

impl Procedural {
    pub const ALL: [Procedural; 6] = [
        Procedural::Sphere,
        Procedural::SphereOverPlane,
        Procedural::Torus,
        Procedural::MarschnerLobb,
        Procedural::Gyroid,
        Procedural::Engine,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Procedural::Sphere => "sphere",
            Procedural::SphereOverPlane => "sphere-over-plane",
            Procedural::Torus => "torus",
            Procedural::MarschnerLobb => "marschner-lobb",
            Procedural::Gyroid => "gyroid",
            Procedural::Engine => "engine",
        }
    }

    /// The iso value at which the volume shows its intended surface.
    pub fn natural_iso(self) -> f64 {
        match self {
            Procedural::MarschnerLobb => 0.5,
            _ => 0.0,
        }
    }

    /// The default size (largest dimension) of each volume.
    pub fn default_size(self) -> usize {
        match self {
            Procedural::MarschnerLobb => 41,
            Procedural::Engine => 256,
            _ => 64,
        }
    }

    /// The grid dimensions for a size (the largest dimension; `None` for the default).
    pub fn dims(self, size: Option<usize>) -> [usize; 3] {
        let n = size.unwrap_or(self.default_size()).max(2);
        match self {
            Procedural::Engine => {
                let nz = ((n as f64 * ENGINE_NZ / ENGINE_NX).round() as usize).max(2);
                [n, n, nz]
            }
            _ => [n, n, n],
        }
    }

    /// Generates the volume; `size` is the largest dimension (default per kind: engine 256 -> 256x256x118).
    pub fn generate(self, size: Option<usize>) -> Volume {
        let dims = self.dims(size);
        let all = crate::VoxelRange::whole(dims);
        self.generate_region(size, &all)
    }

    /// Generates only the samples of `range` (global indices) of the volume of `size`: the crop
    /// of [`Procedural::generate`], sample for sample, without making the rest (object space:
    /// a node holds its brick and halo only). Its origin is the range's first sample.
    pub fn generate_region(self, size: Option<usize>, range: &crate::VoxelRange) -> Volume {
        let dims = self.dims(size);
        let n = dims[0];
        let data = fill_region(range, self.field_fn(dims));
        let name = format!("procedural:{}:{n}", self.name());
        let origin = DVec3::new(range.lo[0] as f64, range.lo[1] as f64, range.lo[2] as f64);
        Volume::new(name, range.dims(), DVec3::ONE, origin, data)
            .expect("procedural volumes are finite and have valid dims")
    }

    /// The field at a sample position (world = voxel index) of the volume of `dims`.
    fn field_fn(self, dims: [usize; 3]) -> Box<dyn Fn(DVec3) -> f64 + Sync> {
        let n = dims[0];
        match self {
            Procedural::Sphere => {
                let c = box_centre(dims);
                let r = 0.35 * (n - 1) as f64;
                Box::new(move |p| r - (p - c).length())
            }
            Procedural::SphereOverPlane => {
                let g = sphere_over_plane_geometry(Some(n));
                Box::new(move |p| g.field(p))
            }
            Procedural::Torus => torus(dims),
            Procedural::MarschnerLobb => {
                let h = 2.0 / (n - 1) as f64;
                Box::new(move |p| marschner_lobb(p * h - DVec3::ONE))
            }
            Procedural::Gyroid => gyroid(dims),
            Procedural::Engine => engine(dims),
        }
    }
}

impl std::str::FromStr for Procedural {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Procedural::ALL.into_iter().find(|p| p.name() == s).ok_or_else(|| {
            let names: Vec<_> = Procedural::ALL.iter().map(|p| p.name()).collect();
            format!("unknown procedural volume '{s}' (one of: {})", names.join(", "))
        })
    }
}

/// The geometry of `sphere-over-plane`, in world units (= voxels): a sphere floating above the
/// half-space `z <= plane_z`. The field is `max(radius - |p - centre|, plane_z - z)` (iso 0), the
/// union of the ball and the half-space (inside the box; the box closes the slab at its faces).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereOverPlane {
    pub centre: DVec3,
    pub radius: f64,
    pub plane_z: f64,
}

/// The geometry `procedural:sphere-over-plane[:size]` is made from (default size 64): a cube of
/// n = size samples per axis, plane at `z0 = 0.25 (n-1)`, radius `r = 0.15 (n-1)`, centre at height
/// `h = 1.6 r` above the plane (so a gap of 0.6 r) and at the box centre in x and y.
pub fn sphere_over_plane_geometry(size: Option<usize>) -> SphereOverPlane {
    let n = size.unwrap_or(Procedural::SphereOverPlane.default_size()).max(2);
    let m = (n - 1) as f64;
    let plane_z = 0.25 * m;
    let radius = 0.15 * m;
    let centre = DVec3::new(0.5 * m, 0.5 * m, plane_z + 1.6 * radius);
    SphereOverPlane { centre, radius, plane_z }
}

impl SphereOverPlane {
    /// The analytic field (signed distance, positive inside) the volume samples.
    pub fn field(&self, p: DVec3) -> f64 {
        (self.radius - (p - self.centre).length()).max(self.plane_z - p.z)
    }

    /// The height `h` of the sphere's centre above the plane.
    pub fn height(&self) -> f64 {
        self.centre.z - self.plane_z
    }

    /// The exact ambient occlusion A (DESIGN.md "AO") at a point on the plane (normal +z), from the
    /// analytic sphere:
    ///
    /// `A = r^2 h / D^3`,
    ///
    /// with r the radius, h the height of the centre above the plane and D the distance from the
    /// point to the centre. This is the form factor from a differential area to a sphere: the sphere
    /// subtends a cone of half-angle alpha with `sin(alpha) = r / D` around a direction at angle
    /// theta from the normal, `cos(theta) = h / D`; the cosine-weighted occluded fraction of the
    /// hemisphere is `sin^2(alpha) cos(theta)`. Directly below the centre it is `(r / h)^2`.
    ///
    /// Valid while the whole sphere is above the point's horizon (always here, as h > r), with the
    /// AO radius at least the tangent length `sqrt(D^2 - r^2)` (or unbounded), since every ray that
    /// meets the sphere enters it within that distance; the plane itself never occludes a point on
    /// it. The rendered volume's sphere is the trilinear interpolant of the samples, which differs
    /// from the analytic sphere by a small fraction of a voxel, so compare with a tolerance.
    pub fn exact_occlusion(&self, point_on_plane: DVec3) -> f64 {
        let d = (self.centre - point_on_plane).length();
        self.radius * self.radius * self.height() / (d * d * d)
    }
}

/// The Marschner-Lobb signal at a point of [-1, 1]^3 (f_M = 6, alpha = 0.25), in [0, 1].
/// Larger towards z = -1: the object `{rho >= 0.5}` is the lower part of the cube, bounded by the
/// rippled surface.
fn marschner_lobb(p: DVec3) -> f64 {
    const F_M: f64 = 6.0;
    const ALPHA: f64 = 0.25;
    let r = (p.x * p.x + p.y * p.y).sqrt();
    let rho_r = (2.0 * PI * F_M * (PI * r / 2.0).cos()).cos();
    (1.0 - (PI * p.z / 2.0).sin() + ALPHA * (1.0 + rho_r)) / (2.0 * (1.0 + ALPHA))
}

/// `sqrt(a^2 + b^2)` (without `hypot`'s overflow care, which costs time and is not needed here).
#[inline]
fn len2(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

fn box_centre(dims: [usize; 3]) -> DVec3 {
    DVec3::new(dims[0] as f64 - 1.0, dims[1] as f64 - 1.0, dims[2] as f64 - 1.0) * 0.5
}

/// Samples `f` at every voxel of `range` (world position = global voxel index), z-slices split
/// over a few threads.
fn fill_region(range: &crate::VoxelRange, f: impl Fn(DVec3) -> f64 + Sync) -> Vec<f32> {
    let [nx, ny, nz] = range.dims();
    let [x0, y0, z0] = range.lo;
    let slice = nx * ny;
    let mut data = vec![0f32; slice * nz];
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 8).min(nz);
    let per = nz.div_ceil(threads);
    let f = &f;
    std::thread::scope(|s| {
        for (c, chunk) in data.chunks_mut(per * slice).enumerate() {
            s.spawn(move || {
                for (dk, plane) in chunk.chunks_mut(slice).enumerate() {
                    let z = (z0 + c * per + dk) as f64;
                    for (j, row) in plane.chunks_mut(nx).enumerate() {
                        let y = (y0 + j) as f64;
                        for (i, v) in row.iter_mut().enumerate() {
                            *v = f(DVec3::new((x0 + i) as f64, y, z)) as f32;
                        }
                    }
                }
            });
        }
    });
    data
}

/// Torus around the z axis through the box centre, tilted 20 degrees about x.
fn torus(dims: [usize; 3]) -> Box<dyn Fn(DVec3) -> f64 + Sync> {
    let m = (dims[0] - 1) as f64;
    let (big, small) = (0.3 * m, 0.12 * m);
    let c = box_centre(dims);
    let (sin, cos) = 20f64.to_radians().sin_cos();
    Box::new(move |p| {
        let d = p - c;
        // Into the torus' frame: rotate by -20 degrees about x.
        let q = DVec3::new(d.x, cos * d.y + sin * d.z, -sin * d.y + cos * d.z);
        let ring = (q.x * q.x + q.y * q.y).sqrt() - big;
        small - (ring * ring + q.z * q.z).sqrt()
    })
}

/// Sheet gyroid, 3 periods across the box, intersected with a ball of radius 0.45 (n-1).
fn gyroid(dims: [usize; 3]) -> Box<dyn Fn(DVec3) -> f64 + Sync> {
    const PERIODS: f64 = 3.0;
    /// Half-thickness of the sheet in units of g (g spans [-1.5, 1.5]).
    const THICKNESS: f64 = 0.5;
    let m = (dims[0] - 1) as f64;
    let k = 2.0 * PI * PERIODS / m; // radians per voxel
    let radius = 0.45 * m;
    let c = box_centre(dims);
    Box::new(move |p| {
        let d = p - c;
        let (x, y, z) = (d.x * k, d.y * k, d.z * k);
        let g = x.sin() * y.cos() + y.sin() * z.cos() + z.sin() * x.cos();
        // |grad g| is about 1 (in radians), so dividing by k gives roughly voxels.
        let sheet = (THICKNESS - g.abs()) / k;
        sheet.min(radius - d.length())
    })
}

/// The engine's design size in x (and y) and z: design units are voxels at the default size.
const ENGINE_NX: f64 = 256.0;
const ENGINE_NZ: f64 = 118.0;
/// Engine values are clamped to +-this many voxels.
const ENGINE_CLAMP: f64 = 8.0;

/// Signed distance (negative inside) to a box of half extents `b` centred at the origin with edges
/// rounded by `r`.
fn rounded_box(p: DVec3, b: DVec3, r: f64) -> f64 {
    let q = p.abs() - b + DVec3::splat(r);
    q.max(DVec3::ZERO).length() + q.max_element().min(0.0) - r
}

/// The engine-like block in design units (centred, voxels at 256x256x118), as insideness (positive
/// inside, 1-Lipschitz): a rounded block with a raised deck on top and a wide base flange, three
/// vertical through bores, stacked cooling fins on both long sides, a bearing boss with a blind hole
/// on the +x end, horizontal bolt holes through both end walls and vertical bolt holes in the flange.
///
/// `reach` (design units; `f64::INFINITY` for the exact CSG) is where the caller clamps: holes that
/// surely lie farther than that are not evaluated, which leaves the clamped value unchanged.
fn engine_design(p: DVec3, reach: f64) -> f64 {
    let inside_box = |c: DVec3, b: DVec3, r: f64| -rounded_box(p - c, b, r);
    // Main block, raised deck (a step) and base flange.
    let body = inside_box(DVec3::new(0.0, 0.0, -5.0), DVec3::new(96.0, 56.0, 38.0), 6.0);
    let deck = inside_box(DVec3::new(0.0, 0.0, 37.0), DVec3::new(86.0, 46.0, 6.0), 3.0);
    let flange = inside_box(DVec3::new(0.0, 0.0, -37.0), DVec3::new(112.0, 80.0, 6.0), 3.0);
    // Cooling fins: horizontal plates 4 thick at a pitch of 8 on both long (y) sides.
    let fins = {
        let (pitch, half_t) = (8.0, 2.0);
        let (first, count) = (-23.0, 7.0);
        let zc = first + 0.5 * (count - 1.0) * pitch;
        let zh = 0.5 * (count - 1.0) * pitch + half_t;
        let q = DVec3::new(p.x, p.y.abs(), p.z);
        let envelope = -rounded_box(q - DVec3::new(0.0, 64.0, zc), DVec3::new(78.0, 10.0, zh), 2.0);
        let t = p.z - first;
        let slab = half_t - (t - pitch * (t / pitch).round()).abs();
        envelope.min(slab)
    };
    // Bearing boss on the +x end: a cylinder along x.
    let boss_axis = DVec3::new(0.0, 0.0, -3.0);
    let boss_r = len2(p.y - boss_axis.y, p.z - boss_axis.z);
    let boss = (15.0 - boss_r).min(112.0 - p.x).min(p.x - 90.0);
    let solid = body.max(deck).max(flange).max(fins).max(boss);

    // Holes (insideness of the empty space). A hole whose insideness is surely <= -(reach + 1)
    // cannot change the clamped value (it only lowers values below what the clamp cuts to), so its
    // square root is skipped; `cyl` bounds it by the larger of the two axis offsets first.
    let skip = reach + 1.0;
    let cyl = |r: f64, a: f64, b: f64| {
        if a.abs().max(b.abs()) - r >= skip {
            f64::NEG_INFINITY
        } else {
            r - len2(a, b)
        }
    };
    let mut hole = f64::NEG_INFINITY;
    for x in [-56.0, 0.0, 56.0] {
        hole = hole.max(cyl(23.0, p.x - x, p.y)); // bores, through
    }
    hole = hole.max((7.0 - boss_r).min(p.x - 84.0)); // blind hole in the boss
    for x in [-88.0, 88.0] {
        for z in [-24.0, 22.0] {
            hole = hole.max(cyl(4.5, p.x - x, p.z - z)); // horizontal bolt holes along y
        }
    }
    // Vertical bolt holes through the flange, ending above it (z < -24).
    if -24.0 - p.z > -skip {
        let flange_hole = |x: f64, y: f64| cyl(4.5, p.x - x, p.y - y).min(-24.0 - p.z);
        for x in [-104.0, 104.0] {
            for y in [-64.0, 0.0, 64.0] {
                hole = hole.max(flange_hole(x, y));
            }
        }
        for x in [-56.0, 0.0, 56.0] {
            for y in [-72.0, 72.0] {
                hole = hole.max(flange_hole(x, y));
            }
        }
    }
    solid.min(-hole)
}

/// Half extents of a box (centred at the design origin) holding the whole solid: every piece's
/// insideness is at most minus its distance to this box along any one axis.
const ENGINE_BOUNDS: DVec3 = DVec3::new(112.0, 80.0, 43.0);

/// The engine's value at a design point, in voxels of a volume `scale` times the design's size,
/// clamped to `[-ENGINE_CLAMP, ENGINE_CLAMP]`.
fn engine_value(q: DVec3, scale: f64) -> f64 {
    // Far outside the solid's bounds the clamped value is known without evaluating the CSG: each
    // piece's insideness is at most -(excess over the bounds along any axis).
    let excess = (q.abs() - ENGINE_BOUNDS).max_element();
    if excess * scale >= ENGINE_CLAMP {
        return -ENGINE_CLAMP;
    }
    (engine_design(q, ENGINE_CLAMP / scale) * scale).clamp(-ENGINE_CLAMP, ENGINE_CLAMP)
}

fn engine(dims: [usize; 3]) -> Box<dyn Fn(DVec3) -> f64 + Sync> {
    let scale = (dims[0] - 1) as f64 / (ENGINE_NX - 1.0);
    let c = box_centre(dims);
    Box::new(move |p| engine_value((p - c) / scale, scale))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straddles(v: &Volume, iso: f64) -> bool {
        let (lo, hi) = v.value_range();
        (lo as f64) < iso && (hi as f64) > iso
    }

    #[test]
    fn procedural_dims_and_names() {
        assert_eq!(Procedural::Sphere.dims(None), [64, 64, 64]);
        assert_eq!(Procedural::SphereOverPlane.dims(None), [64, 64, 64]);
        assert_eq!(Procedural::Torus.dims(None), [64, 64, 64]);
        assert_eq!(Procedural::MarschnerLobb.dims(None), [41, 41, 41]);
        assert_eq!(Procedural::Gyroid.dims(None), [64, 64, 64]);
        assert_eq!(Procedural::Engine.dims(None), [256, 256, 118]);
        assert_eq!(Procedural::Engine.dims(Some(64)), [64, 64, 30]);
        assert_eq!(Procedural::Engine.dims(Some(2)), [2, 2, 2]);
        assert_eq!(Procedural::Engine.dims(Some(1024)), [1024, 1024, 472]);
        let v = Procedural::Torus.generate(Some(20));
        assert_eq!(v.dims(), [20, 20, 20]);
        assert_eq!(v.name, "procedural:torus:20");
        assert_eq!(v.spacing(), DVec3::ONE);
        assert_eq!(v.origin(), DVec3::ZERO);
    }

    #[test]
    fn procedural_all_straddle_their_iso_and_are_finite() {
        for p in Procedural::ALL {
            for size in [2, 3, 24] {
                let v = p.generate(Some(size));
                assert!(v.data().iter().all(|x| x.is_finite()), "{}", v.name);
                if size >= 24 {
                    assert!(straddles(&v, p.natural_iso()), "{} range {:?}", v.name, v.value_range());
                }
            }
        }
        let ml = Procedural::MarschnerLobb.generate(None);
        assert_eq!(ml.dims(), [41, 41, 41]);
        assert!(straddles(&ml, 0.5));
    }

    #[test]
    fn procedural_sphere() {
        let v = Procedural::Sphere.generate(Some(33));
        let r = 0.35 * 32.0;
        assert!(v.at(16, 16, 16) > 0.0);
        assert!((v.at(16, 16, 16) as f64 - r).abs() < 1e-5);
        assert!(v.at(0, 0, 0) < 0.0 && v.at(32, 32, 0) < 0.0);
        // The surface along +x from the centre, by bisection of the trilinear field.
        let (mut a, mut b) = (16.0, 32.0);
        for _ in 0..60 {
            let m = 0.5 * (a + b);
            if v.sample(DVec3::new(m, 16.0, 16.0)).unwrap() >= 0.0 {
                a = m;
            } else {
                b = m;
            }
        }
        assert!((a - 16.0 - r).abs() < 0.5, "surface at {a}, radius {r}");
    }

    #[test]
    fn procedural_sphere_over_plane_geometry_agrees_with_the_field() {
        let n = 40;
        let g = sphere_over_plane_geometry(Some(n));
        let v = Procedural::SphereOverPlane.generate(Some(n));
        let (r, h) = (g.radius, g.height());
        assert!(h > r, "the sphere must float above the plane");
        // Fully inside the box, off the plane.
        assert!(g.centre.z + r < (n - 1) as f64 && g.centre.min_element() - r > 0.0);
        assert!(g.centre.x + r < (n - 1) as f64 && g.centre.y + r < (n - 1) as f64);
        assert!(g.centre.z - r > g.plane_z + 1.0);
        assert!(g.plane_z > 0.0);
        // The voxels are the analytic field; at the centre (a cone point of the distance, which the
        // trilinear interpolant rounds off by under a voxel) the field is the radius.
        let ijk = g.centre.round();
        let voxel = v.at(ijk.x as usize, ijk.y as usize, ijk.z as usize) as f64;
        assert!((voxel - g.field(ijk)).abs() < 1e-5);
        assert!((voxel - r).abs() < 1.0 && (v.sample(g.centre).unwrap() - r).abs() < 1.0);
        let below = DVec3::new(g.centre.x, g.centre.y, g.plane_z);
        assert!(v.sample(below).unwrap().abs() < 1e-5);
        assert!(v.sample(below + DVec3::new(7.3, -3.1, 0.0)).unwrap().abs() < 1e-5);
        // Between the sphere and the plane is empty, above the sphere too, under the plane is inside.
        assert!(v.sample(below + DVec3::Z * (0.5 * (h - r))).unwrap() < 0.0);
        assert!(v.sample(g.centre + DVec3::Z * (r + 1.0)).unwrap() < 0.0);
        assert!(v.sample(below - DVec3::Z).unwrap() > 0.0);
        // Exact AO directly below the centre is (r/h)^2, and falls off sideways.
        let a = g.exact_occlusion(below);
        assert!((a - (r / h).powi(2)).abs() < 1e-12, "{a}");
        assert!(g.exact_occlusion(below + DVec3::X * 5.0) < a);
        // The default geometry is the one the default volume uses.
        let d = sphere_over_plane_geometry(None);
        assert_eq!(d, sphere_over_plane_geometry(Some(64)));
        assert!((d.field(d.centre) - d.radius).abs() < 1e-12);
    }

    #[test]
    fn procedural_sphere_over_plane_exact_occlusion_matches_quadrature() {
        // (1/pi) * integral over the upper hemisphere of V cos(theta) dw, by the midpoint rule in
        // (theta, phi), V from an analytic ray-sphere test.
        let g = sphere_over_plane_geometry(None);
        for offset in [DVec3::ZERO, DVec3::new(6.0, 0.0, 0.0), DVec3::new(-9.0, 12.0, 0.0)] {
            let p = DVec3::new(g.centre.x, g.centre.y, g.plane_z) + offset;
            let (nt, np) = (600, 600);
            let (dt, dp) = (0.5 * PI / nt as f64, 2.0 * PI / np as f64);
            let mut a = 0.0;
            for it in 0..nt {
                let th = (it as f64 + 0.5) * dt;
                for ip in 0..np {
                    let ph = (ip as f64 + 0.5) * dp;
                    let w = DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
                    let oc = g.centre - p;
                    let b = oc.dot(w);
                    if b > 0.0 && oc.length_squared() - b * b <= g.radius * g.radius {
                        a += th.cos() * th.sin() * dt * dp;
                    }
                }
            }
            a /= PI;
            let exact = g.exact_occlusion(p);
            assert!((a - exact).abs() < 2e-3 * exact.max(0.05), "{offset:?}: {a} vs {exact}");
        }
    }

    #[test]
    fn procedural_marschner_lobb_matches_the_formula() {
        let v = Procedural::MarschnerLobb.generate(None);
        // Index (10, 30, 16) on 41 samples is (-0.5, 0.5, -0.2).
        let (x, y, z) = (-0.5f64, 0.5f64, -0.2f64);
        let (f_m, alpha) = (6.0, 0.25);
        let r = (x * x + y * y).sqrt();
        let rho_r = (2.0 * PI * f_m * (PI * r / 2.0).cos()).cos();
        let want = (1.0 - (PI * z / 2.0).sin() + alpha * (1.0 + rho_r)) / (2.0 * (1.0 + alpha));
        assert!((v.at(10, 30, 16) as f64 - want).abs() < 1e-6);
        // Sign: the bottom (z = -1) is inside, the top (z = +1) outside.
        assert!(v.at(20, 20, 0) > 0.5 && v.at(0, 20, 0) > 0.5);
        assert!(v.at(20, 20, 40) < 0.5 && v.at(0, 20, 40) < 0.5);
        let (lo, hi) = v.value_range();
        assert!(lo >= 0.0 && hi <= 1.0);
    }

    #[test]
    fn procedural_torus_and_gyroid() {
        let v = Procedural::Torus.generate(Some(41));
        assert!(v.at(20, 20, 20) < 0.0, "the hole is empty");
        // On the ring (x = R from the centre in the tilted plane, which contains the x axis).
        assert!(v.at(20 + 12, 20, 20) > 4.0);
        let g = Procedural::Gyroid.generate(Some(41));
        assert!(g.at(0, 0, 0) < 0.0, "outside the ball");
        let inside = g.data().iter().filter(|&&x| x >= 0.0).count() as f64 / g.data().len() as f64;
        assert!(inside > 0.05 && inside < 0.5, "{inside}");
    }

    #[test]
    fn procedural_engine_has_bores_body_and_fins() {
        let v = Procedural::Engine.generate(None);
        assert_eq!(v.dims(), [256, 256, 118]);
        assert_eq!(v.name, "procedural:engine:256");
        let c = box_centre(v.dims());
        let at = |x: f64, y: f64, z: f64| v.sample(c + DVec3::new(x, y, z)).unwrap();
        // Bores are empty along their axes through the middle of the block.
        for x in [-56.0, 0.0, 56.0] {
            for z in [-30.0, 0.0, 30.0] {
                assert!(at(x, 0.0, z) < 0.0, "bore at x {x} z {z}");
            }
        }
        // The body between the bores, and the end walls, are solid.
        assert!(at(-28.0, 0.0, 0.0) > 0.0 && at(28.0, 0.0, 0.0) > 0.0);
        assert!(at(0.0, 40.0, 0.0) > 0.0 && at(-90.0, 0.0, 10.0) > 0.0);
        assert!(at(0.0, 0.0, 50.0) < 0.0 && at(120.0, 120.0, 0.0) < 0.0);
        // A vertical line through the fins alternates inside/outside.
        let mut changes = 0;
        let mut prev = at(30.0, 66.0, -58.0) >= 0.0;
        for k in 0..118 {
            let now = at(30.0, 66.0, -58.5 + k as f64) >= 0.0;
            changes += usize::from(now != prev);
            prev = now;
        }
        assert!(changes >= 8, "{changes} changes along the fin line");
        assert!(straddles(&v, 0.0));
        let (lo, hi) = v.value_range();
        assert!(lo >= -8.0 && hi <= 8.0);
        // The same part at a smaller size: bores and body where they belong.
        let s = Procedural::Engine.generate(Some(64));
        assert_eq!(s.dims(), [64, 64, 30]);
        let (cs, k) = (box_centre(s.dims()), 63.0 / 255.0);
        let at = |x: f64, y: f64, z: f64| s.sample(cs + DVec3::new(x, y, z) * k).unwrap();
        assert!(at(0.0, 0.0, 0.0) < 0.0 && at(-28.0, 0.0, 0.0) > 0.0 && at(0.0, 40.0, 0.0) > 0.0);
    }

    #[test]
    fn procedural_engine_early_out_changes_nothing() {
        // Points on a grid spanning beyond the box, at a large, the default and a small scale.
        for scale in [4.0, 1.0, 0.1] {
            for i in -20..=20 {
                for j in -20..=20 {
                    for k in -10..=10 {
                        let q = DVec3::new(i as f64 * 6.5, j as f64 * 6.5, k as f64 * 6.1);
                        let full =
                            (engine_design(q, f64::INFINITY) * scale).clamp(-ENGINE_CLAMP, ENGINE_CLAMP);
                        assert_eq!(engine_value(q, scale), full, "{q:?} at scale {scale}");
                    }
                }
            }
        }
    }
}
