//! Worlds built from scenarios: terrain, ground appearance, the target area and its
//! ground-truth border, all deterministic from the scenario's seed.
//!
//! The ground truth comes from the world itself: the shoreline is the contour of the
//! height field at water level, the cliff region's border is the zero contour of the
//! region function draped on the terrain; both traced by marching squares on a grid
//! finer than the terrain's.

use mavloc_geometry::{nearest_on_polylines, LocalFrame, Vec3};
use noise::{Fbm, MultiFractal, NoiseFn, Perlin};

use crate::scenario::{Scenario, WorldKind};
use crate::terrain::HeightField;
use crate::texture::Texture;

/// What the target area is.
#[derive(Clone, Debug)]
pub enum Target {
    /// Water below `level` (metres of elevation); rendered as a flat, nearly textureless
    /// surface.
    Water { level: f64 },
    /// A region `region(n, e) < 0` of darker ground.
    Region(RegionShape),
    /// No target (indoor floor).
    None,
}

/// A star-shaped region: radius `r0 (1 + sum a_k sin(k theta + phi_k))` around a centre.
#[derive(Clone, Debug)]
pub struct RegionShape {
    pub centre: (f64, f64),
    pub r0: f64,
    pub lobes: Vec<(f64, f64, f64)>, // (k, amplitude, phase)
}

impl RegionShape {
    fn radius(&self, theta: f64) -> f64 {
        self.r0 * (1.0 + self.lobes.iter().map(|(k, a, p)| a * (k * theta + p).sin()).sum::<f64>())
    }

    /// Normalised radial coordinate: < 1 inside, 1 on the border.
    pub fn rho(&self, n: f64, e: f64) -> f64 {
        let (dn, de) = (n - self.centre.0, e - self.centre.1);
        dn.hypot(de) / self.radius(de.atan2(dn))
    }
}

/// A simulated world.
pub struct World {
    pub scenario: Scenario,
    pub frame: LocalFrame,
    pub terrain: HeightField,
    pub target: Target,
    /// Ground-truth border polylines in local NED (closed rings repeat their first point).
    pub ground_truth: Vec<Vec<Vec3>>,
    /// The ground texture: a file's, decoded when the world is built (so a bad file is
    /// named then), or the procedural floor, generated when first sampled: it is 48
    /// million noise evaluations (about a second), and a world that is never rendered
    /// (the simulated vehicle's, a mission plan's, a test's ground truth) does not need it.
    ground: std::sync::OnceLock<Texture>,
    /// Seed and size (texels) of the procedural floor, when the ground is one.
    floor: Option<(u32, usize)>,
    /// Fine procedural detail multiplied over the ground texture: breaks up the tiling
    /// and adds the small-scale texture real ground has.
    detail: Texture,
    /// Half the side of the textured floor (indoor), metres.
    floor_half: f64,
    sun: Vec3,
}

const WATER_RGB: [f32; 3] = [38.0, 62.0, 84.0];
const SKY_RGB: [f32; 3] = [178.0, 202.0, 228.0];
/// Brightness factor of the cliff scenario's target region ("slightly darker").
const REGION_DARKEN: f32 = 0.72;

fn smoothstep(a: f64, b: f64, x: f64) -> f64 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn fbm(seed: u32, octaves: usize) -> Fbm<Perlin> {
    Fbm::<Perlin>::new(seed).set_octaves(octaves)
}

impl World {
    /// Builds the world a scenario describes.
    pub fn build(scenario: &Scenario) -> Result<World, String> {
        scenario.validate()?;
        let seed = scenario.seed as u32;
        let size = scenario.terrain.size_m;
        let cell = scenario.terrain.cell_m;
        // Phases of the shapes from the seed, so each seed gives another world.
        let phase = |k: u32| ((seed.wrapping_mul(2654435761).wrapping_add(k * 40503)) % 6283) as f64 / 1000.0;

        let (terrain, target) = match scenario.kind {
            WorldKind::Coastline => {
                let lake = RegionShape {
                    centre: (0.0, 0.0),
                    r0: 75.0,
                    lobes: vec![
                        (2.0, 0.12, phase(1)),
                        (3.0, 0.10, phase(2)),
                        (5.0, 0.05, phase(3)),
                        (9.0, 0.025, phase(4)),
                    ],
                };
                let hills = fbm(seed, 4);
                let terrain = HeightField::from_fn(size, size, cell, |n, e| {
                    let bank = (4.0 * (lake.rho(n, e) - 1.0)).clamp(-1.5, 1.0);
                    bank + 0.5 * hills.get([n / 60.0, e / 60.0]) + 0.4
                });
                (terrain, Target::Water { level: 0.0 })
            }
            WorldKind::Cliff => {
                let region = RegionShape {
                    centre: (0.0, 0.0),
                    r0: 60.0,
                    lobes: vec![(2.0, 0.10, phase(1)), (3.0, 0.08, phase(2)), (6.0, 0.04, phase(3))],
                };
                let hills = fbm(seed, 4);
                let terrain = HeightField::from_fn(size, size, cell, |n, e| {
                    let edge = 12.0 * (e / 45.0 + phase(5)).sin();
                    25.0 * smoothstep(-14.0, 14.0, n - edge) + 1.2 * hills.get([n / 50.0, e / 50.0])
                });
                (terrain, Target::Region(region))
            }
            WorldKind::IndoorFloor => (HeightField::from_fn(size, size, cell, |_, _| 0.0), Target::None),
        };

        let ground = std::sync::OnceLock::new();
        let floor = match scenario.ground.texture.as_str() {
            // Big enough to cover the 8 x 8 m floor once: a mirrored repeat inside the floor
            // would make two places look alike.
            "" => Some((seed, ((8.2 / scenario.ground.metres_per_texel).ceil() as usize).clamp(64, 2048))),
            name => {
                let _ = ground.set(load_texture(scenario, name)?);
                None
            }
        };
        let detail = detail_texture(seed.wrapping_add(17), 256, scenario.ground.metres_per_texel.min(0.05));

        let mut world = World {
            frame: LocalFrame::new(scenario.origin),
            scenario: scenario.clone(),
            terrain,
            target,
            ground_truth: Vec::new(),
            ground,
            floor,
            detail,
            floor_half: 4.0,
            sun: Vec3::new(-0.45, -0.35, -0.82).normalize(), // towards the sun, from the south-west, high
        };
        world.ground_truth = world.trace_border();
        Ok(world)
    }

    /// Whether ground position (north, east) belongs to the target area.
    pub fn is_target(&self, n: f64, e: f64) -> bool {
        match &self.target {
            Target::Water { level } => self.terrain.height(n, e) < *level,
            Target::Region(r) => r.rho(n, e) < 1.0,
            Target::None => false,
        }
    }

    /// Height of the visible surface: the terrain, or the water surface above it.
    pub fn surface_height(&self, n: f64, e: f64) -> f64 {
        let h = self.terrain.height(n, e);
        match self.target {
            Target::Water { level } => h.max(level),
            _ => h,
        }
    }

    /// Local NED point of the visible surface at (north, east).
    pub fn surface_point(&self, n: f64, e: f64) -> Vec3 {
        Vec3::new(n, e, -self.surface_height(n, e))
    }

    /// Sun lighting factor of a surface with upward normal `normal` (NED).
    pub fn light(&self, normal: &Vec3) -> f32 {
        if matches!(self.scenario.kind, WorldKind::IndoorFloor) {
            1.0 // diffuse indoor light
        } else {
            (0.55 + 0.6 * normal.dot(&self.sun).max(0.0)) as f32
        }
    }

    /// Makes now what rendering makes on its first frame (the procedural floor: seconds
    /// of Perlin noise), for a caller that renders soon and would rather wait before it
    /// starts (a simulated camera before the vehicle takes off).
    pub fn prepare_to_render(&self) {
        if self.floor.is_some() {
            self.ground();
        }
    }

    fn ground(&self) -> &Texture {
        self.ground.get_or_init(|| {
            let (seed, size) = self.floor.expect("a world without a texture file has a procedural floor");
            procedural_floor(seed, size, self.scenario.ground.metres_per_texel)
        })
    }

    /// Colour and target membership of the surface at (north, east) under lighting
    /// `light`: the renderer's per-pixel call, which evaluates the terrain only once.
    pub fn shade_pixel(&self, n: f64, e: f64, footprint: f64, light: f32) -> ([f32; 3], bool) {
        let target = match &self.target {
            Target::Water { level } => {
                if self.terrain.height(n, e) < *level {
                    // Nearly uniform water with faint, large ripples: little for SIFT to hold.
                    let r = self.detail.sample_grey(n * 0.05, e * 0.05, footprint * 0.05) / 255.0 - 0.5;
                    let k = 1.0 + 0.04 * r;
                    return ([WATER_RGB[0] * k, WATER_RGB[1] * k, WATER_RGB[2] * k], true);
                }
                false
            }
            Target::Region(r) => r.rho(n, e) < 1.0,
            Target::None => false,
        };
        if matches!(self.scenario.kind, WorldKind::IndoorFloor)
            && (n.abs() > self.floor_half || e.abs() > self.floor_half)
        {
            return ([118.0, 116.0, 112.0], false); // plain margin around the printed floor
        }
        let base = self.ground().sample(n, e, footprint);
        let detail = 0.85 + 0.3 * self.detail.sample_grey(n, e, footprint) / 255.0;
        let darken = if target { REGION_DARKEN } else { 1.0 };
        let k = detail * light * darken;
        ([(base[0] * k).min(255.0), (base[1] * k).min(255.0), (base[2] * k).min(255.0)], target)
    }

    /// A north-up orthophoto of the ground within `half_extent_m` of the origin, at
    /// `metres_per_px`: `(width, height, RGB)`. Pixel `(u, v)` shows north
    /// `(h - 1) / 2 * m - v * m`, east `u * m - (w - 1) / 2 * m` (centred on the origin).
    /// The indoor seed's orthomap (sec. 3.2), and a floor image for `indoor map-eval`.
    pub fn orthophoto(&self, half_extent_m: f64, metres_per_px: f64) -> (usize, usize, Vec<u8>) {
        let side = ((2.0 * half_extent_m / metres_per_px).round() as usize).max(1);
        let c = (side as f64 - 1.0) / 2.0;
        let light = self.light(&Vec3::new(0.0, 0.0, -1.0));
        let mut rgb = Vec::with_capacity(side * side * 3);
        for v in 0..side {
            for u in 0..side {
                let (n, e) = ((c - v as f64) * metres_per_px, (u as f64 - c) * metres_per_px);
                let (px, _) = self.shade_pixel(n, e, metres_per_px, light);
                rgb.extend(px.iter().map(|x| x.round().clamp(0.0, 255.0) as u8));
            }
        }
        (side, side, rgb)
    }

    /// Colour of a ray that hits nothing.
    pub fn sky(&self) -> [f32; 3] {
        SKY_RGB
    }

    /// Ground-truth border polylines, traced on a grid of half the terrain spacing.
    fn trace_border(&self) -> Vec<Vec<Vec3>> {
        let step = self.terrain.cell / 2.0;
        let half = self.scenario.terrain.size_m / 2.0 - self.terrain.cell;
        let lines = match &self.target {
            Target::Water { level } => {
                let level = *level;
                marching_squares(half, step, |n, e| self.terrain.height(n, e) - level)
            }
            Target::Region(r) => marching_squares(half, step, |n, e| r.rho(n, e) - 1.0),
            Target::None => Vec::new(),
        };
        lines
            .into_iter()
            .filter(|l| l.len() >= 8)
            .map(|l| {
                l.into_iter()
                    .map(|(n, e)| match self.target {
                        Target::Water { level } => Vec3::new(n, e, -level),
                        _ => self.terrain.surface_point(n, e),
                    })
                    .collect()
            })
            .collect()
    }

    /// Nearest point on the ground-truth border to `p`, and its distance (3D).
    pub fn nearest_border_point(&self, p: &Vec3) -> Option<(Vec3, f64)> {
        nearest_on_polylines(&self.ground_truth, p)
    }
}

/// Zero contours of `f` over the square `[-half, half]^2` sampled every `step` metres,
/// as polylines of (north, east). Segments are chained through shared cell edges; a closed
/// contour comes back with its first point repeated at the end.
fn marching_squares(half: f64, step: f64, f: impl Fn(f64, f64) -> f64 + Sync) -> Vec<Vec<(f64, f64)>> {
    use rayon::prelude::*;
    use std::collections::HashMap;
    let count = (2.0 * half / step).floor() as usize + 1;
    let coord = |i: usize| -half + i as f64 * step;
    let values: Vec<f64> =
        (0..count * count).into_par_iter().map(|k| f(coord(k / count), coord(k % count))).collect();
    let v = |i: usize, j: usize| values[i * count + j];
    // An edge is identified by its lower vertex and direction (0: along north, 1: along east).
    type Edge = (usize, usize, u8);
    let point = |e: Edge| -> (f64, f64) {
        let (i, j, dir) = e;
        let (i2, j2) = if dir == 0 { (i + 1, j) } else { (i, j + 1) };
        let (a, b) = (v(i, j), v(i2, j2));
        let t = if a != b { a / (a - b) } else { 0.5 };
        (coord(i) + t * (coord(i2) - coord(i)), coord(j) + t * (coord(j2) - coord(j)))
    };
    let mut links: HashMap<Edge, Vec<Edge>> = HashMap::new();
    for i in 0..count - 1 {
        for j in 0..count - 1 {
            // Corners: 0 (i,j), 1 (i,j+1), 2 (i+1,j+1), 3 (i+1,j); edges between them.
            let inside = [v(i, j) < 0.0, v(i, j + 1) < 0.0, v(i + 1, j + 1) < 0.0, v(i + 1, j) < 0.0];
            let edges: [Edge; 4] = [(i, j, 1), (i, j + 1, 0), (i + 1, j, 1), (i, j, 0)];
            let crossing: Vec<Edge> =
                (0..4).filter(|&k| inside[k] != inside[(k + 1) % 4]).map(|k| edges[k]).collect();
            let pairs: Vec<(Edge, Edge)> = match crossing.len() {
                2 => vec![(crossing[0], crossing[1])],
                4 => {
                    // Saddle: decide by the centre value.
                    let centre = (v(i, j) + v(i, j + 1) + v(i + 1, j + 1) + v(i + 1, j)) / 4.0 < 0.0;
                    if centre == inside[0] {
                        vec![(edges[0], edges[1]), (edges[2], edges[3])]
                    } else {
                        vec![(edges[3], edges[0]), (edges[1], edges[2])]
                    }
                }
                _ => vec![],
            };
            for (a, b) in pairs {
                links.entry(a).or_default().push(b);
                links.entry(b).or_default().push(a);
            }
        }
    }
    let mut lines = Vec::new();
    let mut keys: Vec<Edge> = links.keys().copied().collect();
    keys.sort_unstable();
    // Start open lines at their ends (one link), then take the remaining closed rings.
    let mut starts: Vec<Edge> = keys.iter().copied().filter(|k| links[k].len() == 1).collect();
    starts.extend(keys.iter().copied());
    let mut used: std::collections::HashSet<Edge> = std::collections::HashSet::new();
    for start in starts {
        if used.contains(&start) {
            continue;
        }
        let mut line = vec![point(start)];
        used.insert(start);
        let mut prev = start;
        let mut cur = start;
        loop {
            let next = links[&cur].iter().copied().find(|e| *e != prev && !used.contains(e));
            match next {
                Some(n) => {
                    line.push(point(n));
                    used.insert(n);
                    prev = cur;
                    cur = n;
                }
                None => {
                    if links[&cur].contains(&start) && line.len() > 2 {
                        line.push(point(start));
                    }
                    break;
                }
            }
        }
        lines.push(line);
    }
    lines
}

fn load_texture(scenario: &Scenario, name: &str) -> Result<Texture, String> {
    let built_in: Option<&[u8]> = match name {
        "aukerman.png" => Some(include_bytes!("../assets/aukerman.png")),
        "caliterra.png" => Some(include_bytes!("../assets/caliterra.png")),
        _ => None,
    };
    let mpt = scenario.ground.metres_per_texel;
    match built_in {
        Some(bytes) => Texture::decode(bytes, mpt).map_err(|e| format!("built-in texture {name}: {e}")),
        None => {
            let path = match &scenario.base_dir {
                Some(dir) => dir.join(name),
                None => name.into(),
            };
            Texture::load(&path, mpt)
        }
    }
}

/// Grey-level multi-scale noise used as fine ground detail.
fn detail_texture(seed: u32, size: usize, metres_per_texel: f64) -> Texture {
    let noise = fbm(seed, 5);
    let rgb = (0..size * size)
        .map(|k| {
            let (x, y) = ((k % size) as f64, (k / size) as f64);
            let v = (noise.get([x / 24.0, y / 24.0]) * 0.5 + 0.5).clamp(0.0, 1.0) as f32 * 255.0;
            [v, v, v]
        })
        .collect();
    Texture::from_rgb(size, size, rgb, metres_per_texel)
}

/// A rich, non-repeating floor pattern: coloured blobs and strokes of several sizes over
/// multi-octave colour noise (the indoor seed's floors are printed textures, fig. 3.5).
fn procedural_floor(seed: u32, size: usize, metres_per_texel: f64) -> Texture {
    use rand::{Rng, SeedableRng};
    use rayon::prelude::*;
    let channels = [fbm(seed, 6), fbm(seed + 1, 6), fbm(seed + 2, 6)];
    // Each texel's noise is its own (48 million evaluations in all): on every core.
    let mut rgb: Vec<[f32; 3]> = (0..size * size)
        .into_par_iter()
        .map(|k| {
            let (x, y) = ((k % size) as f64 / 90.0, (k / size) as f64 / 90.0);
            let mut c = [0.0f32; 3];
            for (ch, n) in channels.iter().enumerate() {
                c[ch] = ((n.get([x, y]) * 0.5 + 0.5).clamp(0.0, 1.0) * 170.0 + 40.0) as f32;
            }
            c
        })
        .collect();
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed as u64);
    let blobs = 900 * size * size / (1024 * 1024);
    for _ in 0..blobs {
        let (cx, cy) = (rng.random_range(0.0..size as f64), rng.random_range(0.0..size as f64));
        let r = rng.random_range(3.0..28.0f64);
        let colour = [
            rng.random_range(0.0..255.0f32),
            rng.random_range(0.0..255.0f32),
            rng.random_range(0.0..255.0f32),
        ];
        let aspect = rng.random_range(0.3..1.0f64);
        let angle = rng.random_range(0.0..std::f64::consts::PI);
        let (s, c) = angle.sin_cos();
        let reach = r.ceil() as i64 + 1;
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let (x, y) = (cx as i64 + dx, cy as i64 + dy);
                if x < 0 || y < 0 || x >= size as i64 || y >= size as i64 {
                    continue;
                }
                let (fx, fy) = (x as f64 - cx, y as f64 - cy);
                let (u, w) = (fx * c + fy * s, (-fx * s + fy * c) / aspect);
                if u * u + w * w <= r * r {
                    rgb[y as usize * size + x as usize] = colour;
                }
            }
        }
    }
    Texture::from_rgb(size, size, rgb, metres_per_texel)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;

    #[test]
    fn marching_squares_traces_a_circle() {
        let lines = marching_squares(20.0, 0.5, |n, e| n.hypot(e) - 10.0);
        assert_eq!(lines.len(), 1);
        let ring = &lines[0];
        assert_eq!(ring.first(), ring.last(), "closed ring repeats its first point");
        for (n, e) in ring {
            assert!((n.hypot(*e) - 10.0).abs() < 0.02, "({n}, {e})");
        }
        let length: f64 = ring.windows(2).map(|w| (w[1].0 - w[0].0).hypot(w[1].1 - w[0].1)).sum();
        assert!((length - 2.0 * std::f64::consts::PI * 10.0).abs() < 0.5, "{length}");
    }

    #[test]
    fn coastline_ground_truth_is_the_shore() {
        let world = World::build(&Scenario::load("coastline").unwrap()).unwrap();
        assert!(!world.ground_truth.is_empty());
        let ring = world.ground_truth.iter().max_by_key(|l| l.len()).unwrap();
        assert!(ring.len() > 400);
        for p in ring.iter().step_by(17) {
            assert!((p.z).abs() < 1e-9, "shore at water level");
            assert!(world.terrain.height(p.x, p.y).abs() < 0.05);
            // Water on one side, land on the other, within a metre.
            let r = p.x.hypot(p.y);
            let (un, ue) = (p.x / r, p.y / r);
            assert!(world.is_target(p.x - un, p.y - ue) != world.is_target(p.x + un, p.y + ue));
        }
    }

    #[test]
    fn cliff_border_runs_over_the_slope() {
        let world = World::build(&Scenario::load("cliff").unwrap()).unwrap();
        let ring = world.ground_truth.iter().max_by_key(|l| l.len()).unwrap();
        let downs: Vec<f64> = ring.iter().map(|p| p.z).collect();
        let (lo, hi) =
            downs.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &d| (a.min(d), b.max(d)));
        assert!(hi - lo > 15.0, "border spans {:.1} m of height", hi - lo);
    }

    /// The indoor floor is generated when first shaded, not when the world is built, and
    /// only once; a texture file is read at build time.
    #[test]
    fn the_procedural_floor_waits_for_the_first_pixel() {
        let mut s = Scenario::load("indoor-floor").unwrap();
        s.ground.metres_per_texel = 0.02; // a coarse floor: quicker, as lazy

        let a = World::build(&s).unwrap();
        assert!(a.ground.get().is_none(), "generated by build");
        let pixel = a.shade_pixel(1.3, -2.1, 0.004, 1.0);
        assert!(a.ground.get().is_some());
        // Generated once: later pixels read the same floor.
        let floor: *const Texture = a.ground.get().unwrap();
        assert_eq!(a.shade_pixel(1.3, -2.1, 0.004, 1.0), pixel);
        assert!(std::ptr::eq(a.ground(), floor));
        let coast = World::build(&Scenario::load("coastline").unwrap()).unwrap();
        assert!(coast.ground.get().is_some(), "a texture file waits for nothing");
    }

    #[test]
    fn worlds_are_deterministic() {
        let s = Scenario::load("cliff").unwrap();
        let (a, b) = (World::build(&s).unwrap(), World::build(&s).unwrap());
        assert_eq!(a.ground_truth[0].len(), b.ground_truth[0].len());
        assert_eq!(a.shade_pixel(3.0, -4.0, 0.1, 1.0), b.shade_pixel(3.0, -4.0, 0.1, 1.0));
    }
}
