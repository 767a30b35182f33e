//! The camera renderer: a z-buffered rasteriser of the world's surface mesh, then one
//! shading pass per pixel from the world position it sees.
//!
//! Vertices go through `mavloc-geometry`'s own transform and projection (the rotation of
//! `CameraPose::to_camera`, composed once a frame, and `Intrinsics::project_camera`), so
//! rendered pixels and the pipeline's geometry agree by construction; a test checks it to
//! a fraction of a pixel. Triangles are clipped against a near plane in camera space,
//! interpolation is perspective-correct, and the image is split into row bands rendered in
//! parallel. Cells are first culled in square blocks against the view frustum: a frame
//! sees a small part of the terrain, and clipping and projecting every triangle of it was
//! over a quarter of the CPU a `mavloc run` with the simulated camera spent at 480x270
//! (`perf`). Each pixel is shaded once (deferred), from the world's texture at a mip level
//! matched to the pixel's ground footprint.

use mavloc_geometry::{CameraPose, Intrinsics, Vec3};
use rayon::prelude::*;

use crate::world::World;

/// A rendered frame: RGB (row-major, 3 bytes per pixel) and the target mask (255 inside
/// the target area, 0 elsewhere), as AirSim's scene and segmentation images.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
    pub mask: Vec<u8>,
}

/// A coloured disk painted on the ground, for tests that need to find a known 3D point in
/// the image.
#[derive(Clone, Copy, Debug)]
pub struct Marker {
    pub centre: Vec3,
    pub radius_m: f64,
    pub rgb: [u8; 3],
}

/// Renders frames of one world.
pub struct Renderer<'w> {
    world: &'w World,
    /// Surface vertices (terrain, or water surface where it is higher), local NED.
    vertices: Vec<Vec3>,
    rows: usize,
    cols: usize,
    /// Sun lighting of each triangle (two per cell), fixed for the world.
    light: Vec<f32>,
    /// Bounding boxes of the surface in blocks of `BLOCK` x `BLOCK` cells, row-major.
    blocks: Vec<Bounds>,
    block_cols: usize,
    pub markers: Vec<Marker>,
}

const NEAR: f64 = 0.05;

/// Side of a culling block, in cells: 64 cells to a test of 8 corners.
const BLOCK: usize = 8;

/// An axis-aligned box in local NED.
#[derive(Clone, Copy, Debug)]
struct Bounds {
    lo: Vec3,
    hi: Vec3,
}

#[derive(Clone, Copy, Debug)]
struct ClipVert {
    cam: Vec3,
    n: f64,
    e: f64,
}

#[derive(Clone, Copy, Debug)]
struct ScreenVert {
    u: f64,
    v: f64,
    inv_z: f64,
    n_z: f64,
    e_z: f64,
}

#[derive(Clone, Copy, Debug)]
struct Prepared {
    v: [ScreenVert; 3],
    light: f32,
    area: f64,
    x0: i64,
    x1: i64,
    y0: i64,
    y1: i64,
}

#[derive(Clone, Copy, Debug, Default)]
struct Texel {
    inv_z: f32,
    n: f32,
    e: f32,
    light: f32,
}

impl<'w> Renderer<'w> {
    pub fn new(world: &'w World) -> Renderer<'w> {
        let t = &world.terrain;
        let vertices = (0..t.rows * t.cols)
            .map(|k| {
                let (i, j) = (k / t.cols, k % t.cols);
                let v = t.vertex(i, j);
                world.surface_point(v.x, v.y)
            })
            .collect::<Vec<Vec3>>();
        let (rows, cols) = (t.rows, t.cols);
        let light = (0..(rows - 1) * (cols - 1) * 2)
            .map(|k| {
                let (cell, second) = (k / 2, k % 2 == 1);
                let (i, j) = (cell / (cols - 1), cell % (cols - 1));
                let at = |i: usize, j: usize| vertices[i * cols + j];
                let (a, b, c) = if second {
                    (at(i, j), at(i + 1, j + 1), at(i, j + 1))
                } else {
                    (at(i, j), at(i + 1, j), at(i + 1, j + 1))
                };
                let mut normal = (b - a).cross(&(c - a)).normalize();
                if normal.z > 0.0 {
                    normal = -normal; // upward is negative down
                }
                world.light(&normal)
            })
            .collect();
        let block_rows = (rows - 1).div_ceil(BLOCK);
        let block_cols = (cols - 1).div_ceil(BLOCK);
        let blocks = (0..block_rows * block_cols)
            .map(|b| {
                let (bi, bj) = (b / block_cols, b % block_cols);
                let mut bounds =
                    Bounds { lo: Vec3::repeat(f64::INFINITY), hi: Vec3::repeat(f64::NEG_INFINITY) };
                for i in bi * BLOCK..=((bi + 1) * BLOCK).min(rows - 1) {
                    for j in bj * BLOCK..=((bj + 1) * BLOCK).min(cols - 1) {
                        let v = vertices[i * cols + j];
                        bounds = Bounds { lo: bounds.lo.inf(&v), hi: bounds.hi.sup(&v) };
                    }
                }
                bounds
            })
            .collect();
        Renderer { world, vertices, rows, cols, light, blocks, block_cols, markers: Vec::new() }
    }

    /// Renders the view of a camera with intrinsics `k` at `pose`.
    pub fn render(&self, pose: &CameraPose, k: &Intrinsics) -> Frame {
        let (w, h) = (k.width as usize, k.height as usize);
        let tris = self.prepare(pose, k);

        // Bands of rows, a few per thread so uneven bands balance out.
        let bands = (rayon::current_num_threads() * 4).clamp(1, h);
        let band_rows = h.div_ceil(bands);
        let mut gbuf = vec![Texel::default(); w * h];
        gbuf.par_chunks_mut(band_rows * w).enumerate().for_each(|(b, chunk)| {
            let y0 = (b * band_rows) as i64;
            let y1 = y0 + (chunk.len() / w) as i64 - 1;
            for t in &tris {
                if t.y1 < y0 || t.y0 > y1 {
                    continue;
                }
                raster(t, y0.max(t.y0), y1.min(t.y1), y0, w, chunk);
            }
        });

        let mut rgb = vec![0u8; w * h * 3];
        let mut mask = vec![0u8; w * h];
        let fx = k.fx;
        rgb.par_chunks_mut(w * 3).zip(mask.par_chunks_mut(w)).enumerate().for_each(|(y, (row, mrow))| {
            for x in 0..w {
                let g = gbuf[y * w + x];
                let (colour, target) = if g.inv_z > 0.0 {
                    let (n, e) = (g.n as f64, g.e as f64);
                    // Ground footprint of the pixel: its size at that depth, stretched by
                    // the slant (bounded so grazing views do not blur to nothing).
                    let depth = 1.0 / g.inv_z as f64;
                    let footprint = depth / fx * 1.5;
                    let (colour, target) = self.world.shade_pixel(n, e, footprint, g.light);
                    (self.marker_at(n, e).unwrap_or(colour), target)
                } else {
                    (self.world.sky(), false)
                };
                for c in 0..3 {
                    row[3 * x + c] = colour[c].round().clamp(0.0, 255.0) as u8;
                }
                mrow[x] = if target { 255 } else { 0 };
            }
        });
        Frame { width: k.width, height: k.height, rgb, mask }
    }

    fn marker_at(&self, n: f64, e: f64) -> Option<[f32; 3]> {
        self.markers.iter().find_map(|m| {
            let d = (n - m.centre.x).hypot(e - m.centre.y);
            (d <= m.radius_m).then(|| [m.rgb[0] as f32, m.rgb[1] as f32, m.rgb[2] as f32])
        })
    }

    /// Clips, projects and bounds every triangle that can appear on screen, in the order
    /// of the cells (row by row), so depth ties resolve as they always did.
    fn prepare(&self, pose: &CameraPose, k: &Intrinsics) -> Vec<Prepared> {
        let (w, h) = (k.width as i64, k.height as i64);
        let cols = self.cols;
        // `CameraPose::to_camera` with the rotation composed once per frame, not per vertex,
        // and the product written out: nalgebra's generic one was not inlined here, and with
        // the vertices' repeated transforms it was a third of a small frame's time. The sums
        // run in nalgebra's order (column by column), so the pixels are the same.
        let m = *pose.local_from_camera().inverse().matrix();
        let origin = pose.position;
        let to_camera = move |p: &Vec3| {
            let d = p - origin;
            Vec3::new(
                m[(0, 0)] * d.x + m[(0, 1)] * d.y + m[(0, 2)] * d.z,
                m[(1, 0)] * d.x + m[(1, 1)] * d.y + m[(1, 2)] * d.z,
                m[(2, 0)] * d.x + m[(2, 1)] * d.y + m[(2, 2)] * d.z,
            )
        };
        let shown: Vec<bool> = self.blocks.par_iter().map(|b| may_show(b, &to_camera, k)).collect();
        (0..self.rows - 1)
            .into_par_iter()
            .fold(Vec::new, |mut out, i| {
                let corner = |i: usize, j: usize| {
                    let p = self.vertices[i * cols + j];
                    ClipVert { cam: to_camera(&p), n: p.x, e: p.y }
                };
                let blocks = &shown[(i / BLOCK) * self.block_cols..][..self.block_cols];
                for (bj, _) in blocks.iter().enumerate().filter(|(_, shown)| **shown) {
                    // The block's two rows of corners, each transformed once (not once for
                    // each of the four cells around it).
                    let (j0, j1) = (bj * BLOCK, ((bj + 1) * BLOCK).min(cols - 1));
                    // A corner in front of the near plane is projected once too: a triangle
                    // wholly in front (nearly all) needs no clipping, and its setup reads the
                    // projections (the same arithmetic as `setup`, so the same pixels).
                    let mut top = [(ClipVert { cam: Vec3::zeros(), n: 0.0, e: 0.0 }, None); BLOCK + 1];
                    let mut bottom = top;
                    for j in j0..=j1 {
                        for (row, slot) in [(i, &mut top[j - j0]), (i + 1, &mut bottom[j - j0])] {
                            let c = corner(row, j);
                            *slot = (c, (c.cam.z >= NEAR).then(|| screen(&c, k)).flatten());
                        }
                    }
                    for j in j0..j1 {
                        let q = j - j0;
                        let (a, b, c, d) = (top[q], bottom[q], bottom[q + 1], top[q + 1]);
                        let cell = i * (cols - 1) + j;
                        for (t, tri) in [[a, b, c], [a, c, d]].into_iter().enumerate() {
                            let light = self.light[2 * cell + t];
                            if tri.iter().all(|v| v.0.cam.z >= NEAR) {
                                // What clipping would return: the triangle itself.
                                if let [(_, Some(sa)), (_, Some(sb)), (_, Some(sc))] = tri {
                                    if let Some(p) = setup_screen([sa, sb, sc], light, w, h) {
                                        out.push(p);
                                    }
                                }
                                continue;
                            }
                            let tri = tri.map(|v| v.0);
                            if tri.iter().all(|v| v.cam.z < NEAR) {
                                continue;
                            }
                            let (poly, len) = clip_near(&tri);
                            for f in 1..len.saturating_sub(1) {
                                if let Some(p) = setup([poly[0], poly[f], poly[f + 1]], light, k, w, h) {
                                    out.push(p);
                                }
                            }
                        }
                    }
                }
                out
            })
            .reduce(Vec::new, |mut a, mut b| {
                a.append(&mut b);
                a
            })
    }
}

/// Whether anything in a box can cover a pixel centre: false when all eight corners lie
/// outside one plane of the view frustum (the near plane, or the plane through the
/// camera and an image edge moved out by a pixel). The box is convex, so everything in
/// it, clipped triangles included, is then outside that plane too.
fn may_show(b: &Bounds, to_camera: &impl Fn(&Vec3) -> Vec3, k: &Intrinsics) -> bool {
    let (w, h) = (k.width as f64, k.height as f64);
    let corners = (0..8).map(|c| {
        let pick = |bit: usize, lo: f64, hi: f64| if c & bit == 0 { lo } else { hi };
        to_camera(&Vec3::new(pick(1, b.lo.x, b.hi.x), pick(2, b.lo.y, b.hi.y), pick(4, b.lo.z, b.hi.z)))
    });
    // In the camera frame (x right, y down, z forward) a point with z > 0 projects left
    // of u = -1 exactly when fx x + (cx + 1) z < 0, right of u = w when
    // fx x + (cx - w) z > 0; the same in y. Pixel centres lie in [0, w - 1].
    let mut all_out = [true; 5];
    for p in corners {
        let tests = [
            p.z < NEAR,
            k.fx * p.x + (k.cx + 1.0) * p.z < 0.0,
            k.fx * p.x + (k.cx - w) * p.z > 0.0,
            k.fy * p.y + (k.cy + 1.0) * p.z < 0.0,
            k.fy * p.y + (k.cy - h) * p.z > 0.0,
        ];
        for (all, out) in all_out.iter_mut().zip(tests) {
            *all &= out;
        }
    }
    !all_out.iter().any(|&all| all)
}

/// Sutherland-Hodgman clip of a triangle against `z >= NEAR` in camera space: at most
/// four vertices, kept on the stack.
fn clip_near(tri: &[ClipVert; 3]) -> ([ClipVert; 4], usize) {
    let mut out = [tri[0]; 4];
    let mut len = 0;
    for i in 0..3 {
        let (a, b) = (tri[i], tri[(i + 1) % 3]);
        let (ina, inb) = (a.cam.z >= NEAR, b.cam.z >= NEAR);
        if ina {
            out[len] = a;
            len += 1;
        }
        if ina != inb {
            let t = (NEAR - a.cam.z) / (b.cam.z - a.cam.z);
            out[len] = ClipVert {
                cam: a.cam + (b.cam - a.cam) * t,
                n: a.n + (b.n - a.n) * t,
                e: a.e + (b.e - a.e) * t,
            };
            len += 1;
        }
    }
    (out, len)
}

/// A vertex on the image plane, with what the rasteriser interpolates (`None` when it does
/// not project: behind the camera or not finite).
fn screen(c: &ClipVert, k: &Intrinsics) -> Option<ScreenVert> {
    let px = k.project_camera(&c.cam)?;
    let iz = 1.0 / c.cam.z;
    Some(ScreenVert { u: px.u, v: px.v, inv_z: iz, n_z: c.n * iz, e_z: c.e * iz })
}

fn setup(tri: [ClipVert; 3], light: f32, k: &Intrinsics, w: i64, h: i64) -> Option<Prepared> {
    let [a, b, c] = tri;
    setup_screen([screen(&a, k)?, screen(&b, k)?, screen(&c, k)?], light, w, h)
}

/// A projected triangle's edge function and the pixel centres it may cover.
fn setup_screen(v: [ScreenVert; 3], light: f32, w: i64, h: i64) -> Option<Prepared> {
    let area = edge(&v[0], &v[1], v[2].u, v[2].v);
    if area.abs() < 1e-12 {
        return None;
    }
    let min = |f: fn(&ScreenVert) -> f64| v.iter().map(f).fold(f64::INFINITY, f64::min);
    let max = |f: fn(&ScreenVert) -> f64| v.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
    // Pixel centres are at integers: cover the centres inside the bounding box.
    let x0 = (min(|s| s.u).ceil() as i64).max(0);
    let x1 = (max(|s| s.u).floor() as i64).min(w - 1);
    let y0 = (min(|s| s.v).ceil() as i64).max(0);
    let y1 = (max(|s| s.v).floor() as i64).min(h - 1);
    (x0 <= x1 && y0 <= y1).then_some(Prepared { v, light, area, x0, x1, y0, y1 })
}

fn edge(a: &ScreenVert, b: &ScreenVert, x: f64, y: f64) -> f64 {
    (b.u - a.u) * (y - a.v) - (b.v - a.v) * (x - a.u)
}

/// Rasterises rows `ya..=yb` of a triangle into a band starting at row `band_y0`.
fn raster(t: &Prepared, ya: i64, yb: i64, band_y0: i64, w: usize, band: &mut [Texel]) {
    let [a, b, c] = t.v;
    let inv_area = 1.0 / t.area;
    for y in ya..=yb {
        let yf = y as f64;
        let row = &mut band[(y - band_y0) as usize * w..][..w];
        for x in t.x0..=t.x1 {
            let xf = x as f64;
            let w0 = edge(&b, &c, xf, yf) * inv_area;
            let w1 = edge(&c, &a, xf, yf) * inv_area;
            let w2 = 1.0 - w0 - w1;
            // Inside test with a little tolerance so shared edges leave no cracks.
            if w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9 {
                continue;
            }
            let inv_z = w0 * a.inv_z + w1 * b.inv_z + w2 * c.inv_z;
            let texel = &mut row[x as usize];
            if inv_z as f32 > texel.inv_z {
                let n = (w0 * a.n_z + w1 * b.n_z + w2 * c.n_z) / inv_z;
                let e = (w0 * a.e_z + w1 * b.e_z + w2 * c.e_z) / inv_z;
                *texel = Texel { inv_z: inv_z as f32, n: n as f32, e: e as f32, light: t.light };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;
    use mavloc_geometry::{GimbalAngles, GimbalChain, Mount};

    fn small(k: &Intrinsics) -> Intrinsics {
        k.downscaled(4)
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(24))]
        /// Frustum culling changes no pixel: any camera over the coastline or the cliff
        /// (25 m of relief), from straight down to above the horizon, from just over the
        /// ground to high above, renders byte for byte as with every block shown (each
        /// block's box widened to the whole world's, which no frustum plane can leave out).
        #[test]
        fn culling_changes_no_pixel(
            cliff in proptest::bool::ANY,
            n in -200.0..200.0f64, e in -200.0..200.0f64, up in 0.5..150.0f64,
            yaw in -180.0..180.0f64, pitch in -90.0..15.0f64, roll in -20.0..20.0f64,
        ) {
            let world = shared_world(if cliff { "cliff" } else { "coastline" });
            let culled = Renderer::new(world);
            let mut whole = Renderer::new(world);
            let all = whole.blocks.iter().fold(whole.blocks[0], |a, b| Bounds { lo: a.lo.inf(&b.lo), hi: a.hi.sup(&b.hi) });
            whole.blocks.iter_mut().for_each(|b| *b = all);
            let k = Intrinsics::from_hfov(160, 90, 90f64.to_radians());
            let ground = world.surface_point(n, e);
            let angles = GimbalAngles::from_degrees(yaw, pitch, roll);
            let pose = CameraPose::from_gimbal(ground - Vec3::z() * up, GimbalChain::YawPitchRoll, angles, Mount::Earth);
            let (a, b) = (culled.render(&pose, &k), whole.render(&pose, &k));
            proptest::prop_assert!(a.rgb == b.rgb && a.mask == b.mask, "{pose:?}");
        }
    }

    /// The outdoor worlds, each built once for the property test's cases.
    fn shared_world(name: &str) -> &'static World {
        static COASTLINE: std::sync::OnceLock<World> = std::sync::OnceLock::new();
        static CLIFF: std::sync::OnceLock<World> = std::sync::OnceLock::new();
        let cell = if name == "cliff" { &CLIFF } else { &COASTLINE };
        cell.get_or_init(|| World::build(&Scenario::load(name).unwrap()).unwrap())
    }

    /// The projection-agreement test: a marked 3D point appears within 0.5 px of where
    /// the geometry module projects it.
    #[test]
    fn marked_point_lands_where_geometry_projects_it() {
        for name in ["coastline", "cliff"] {
            let scenario = Scenario::load(name).unwrap();
            let world = World::build(&scenario).unwrap();
            let mut renderer = Renderer::new(&world);
            let k = small(&scenario.intrinsics());
            for (n, e, yaw, pitch) in
                [(-50.0, 30.0, 20.0, -60.0), (40.0, -70.0, -150.0, -35.0), (0.0, 0.0, 90.0, -89.0)]
            {
                let centre = world.surface_point(n, e);
                renderer.markers = vec![Marker { centre, radius_m: 0.35, rgb: [255, 0, 255] }];
                // Camera 30 m above and back along the view direction.
                let angles = GimbalAngles::from_degrees(yaw, pitch, 0.0);
                let dir = GimbalChain::YawPitchRoll.rotation(angles) * Vec3::x();
                let pose = CameraPose::from_gimbal(
                    centre - dir * 40.0,
                    GimbalChain::YawPitchRoll,
                    angles,
                    Mount::Earth,
                );
                let expected = pose.project(&k, &centre).unwrap();
                let frame = renderer.render(&pose, &k);
                let (mut su, mut sv, mut count) = (0.0, 0.0, 0.0);
                for y in 0..frame.height as usize {
                    for x in 0..frame.width as usize {
                        let p = &frame.rgb[3 * (y * frame.width as usize + x)..][..3];
                        if p == [255, 0, 255] {
                            su += x as f64;
                            sv += y as f64;
                            count += 1.0;
                        }
                    }
                }
                assert!(count >= 3.0, "{name}: marker covers {count} px");
                let (u, v) = (su / count, sv / count);
                let err = (u - expected.u).hypot(v - expected.v);
                assert!(
                    err < 0.5,
                    "{name} at ({n}, {e}): centroid ({u:.2}, {v:.2}) vs ({:.2}, {:.2})",
                    expected.u,
                    expected.v
                );
            }
        }
    }

    #[test]
    fn body_mounted_nadir_camera_has_north_up() {
        let mut scenario = Scenario::load("indoor-floor").unwrap();
        // A coarse floor (1/16 of the texels to generate): the marker is what is looked at.
        scenario.ground.metres_per_texel = 0.02;
        let world = World::build(&scenario).unwrap();
        let mut renderer = Renderer::new(&world);
        let k = Intrinsics::from_hfov(64, 48, 70f64.to_radians());
        let centre = Vec3::new(1.0, 2.0, 0.0);
        renderer.markers =
            vec![Marker { centre: centre + Vec3::new(0.3, 0.0, 0.0), radius_m: 0.05, rgb: [255, 0, 255] }];
        let attitude = mavloc_geometry::body_rotation(0.0, 0.0, 0.0);
        let pose = CameraPose::from_gimbal(
            centre - Vec3::new(0.0, 0.0, 1.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(0.0, -90.0, 0.0),
            Mount::Body { attitude },
        );
        let frame = renderer.render(&pose, &k);
        let hits: Vec<(usize, usize)> = (0..48 * 64)
            .filter(|i| frame.rgb[3 * i..3 * i + 3] == [255, 0, 255])
            .map(|i| (i % 64, i / 64))
            .collect();
        assert!(!hits.is_empty());
        let (u, v) = hits[hits.len() / 2];
        assert!(v < 20 && (u as i64 - 32).abs() <= 2, "north marker at ({u}, {v})");
    }

    #[test]
    fn nadir_over_the_lake_sees_water_in_the_mask() {
        let scenario = Scenario::load("coastline").unwrap();
        let world = World::build(&scenario).unwrap();
        let renderer = Renderer::new(&world);
        let k = small(&scenario.intrinsics());
        let pose = CameraPose::from_gimbal(
            Vec3::new(0.0, 0.0, -30.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(0.0, -90.0, 0.0),
            Mount::Earth,
        );
        let frame = renderer.render(&pose, &k);
        let water = frame.mask.iter().filter(|&&m| m == 255).count();
        assert_eq!(water, frame.mask.len(), "the lake centre is all water");
        // Looking at the horizon: sky at the top, no target there.
        let pose = CameraPose::from_gimbal(
            Vec3::new(0.0, 0.0, -30.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(0.0, 0.0, 0.0),
            Mount::Earth,
        );
        let frame = renderer.render(&pose, &k);
        let top = &frame.rgb[..3];
        assert_eq!(top, [178, 202, 228], "sky colour at the top");
        assert_eq!(frame.mask[0], 0);
    }

    #[test]
    fn mask_agrees_with_the_world_at_pixel_rays() {
        let scenario = Scenario::load("cliff").unwrap();
        let world = World::build(&scenario).unwrap();
        let renderer = Renderer::new(&world);
        let k = small(&scenario.intrinsics());
        let pose =
            CameraPose::looking_at(Vec3::new(-90.0, 10.0, -45.0), &world.surface_point(-20.0, 0.0)).unwrap();
        let frame = renderer.render(&pose, &k);
        let inside = frame.mask.iter().filter(|&&m| m == 255).count();
        assert!(inside > 100 && inside < frame.mask.len() - 100, "the view straddles the border");
    }
}
