//! Datasets on disk: the one format the pipelines, `mavloc eval` and the daemon's replay
//! camera read.
//!
//! ```text
//! DIR/
//!   frames/NNNNNN.png      RGB frames (.jpg for imported photos)
//!   masks/NNNNNN.png       target masks (255 inside the target area, 0 outside)
//!   telemetry.jsonl        one JSON object per frame: time, true and measured pose, gimbal
//!   camera.toml            intrinsics, resolution, gimbal kinematic chain
//!   ground_truth.csv       border polylines: line, index, north, east, down, lat, lon, alt
//!   ground_truth.geojson   the same in WGS84 (RFC 7946: lon, lat, alt)
//!   scenario.toml          everything needed to re-render the dataset
//!   mission.plan           the flight as a QGroundControl plan
//!   mavloc.toml            optional: settings the data needs, layered over the
//!                          configuration file by `mavloc area` (imported photos have one)
//! ```
//!
//! Files are written to a temporary name and renamed, so a crash leaves either the old file
//! or the complete new one; `telemetry.jsonl` is written last, so a dataset whose render
//! was interrupted is recognisably incomplete.

use std::fs;
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};

use mavloc_geometry::{GimbalAngles, GimbalChain, Intrinsics, LocalFrame, Vec3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::mission::{GimbalFrame, Mission, State};
use crate::render::Renderer;
use crate::scenario::{NoiseSpec, Scenario};
use crate::world::World;

/// Settings a dataset carries for the commands that run on it (see the module doc).
pub const SETTINGS_FILE: &str = "mavloc.toml";

/// A pose as the dataset records it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseRecord {
    /// Local NED position, metres.
    pub position: [f64; 3],
    /// Vehicle roll, pitch, yaw, degrees.
    pub attitude_deg: [f64; 3],
    /// Gimbal yaw, pitch, roll in the camera's kinematic chain, degrees.
    pub gimbal_deg: [f64; 3],
    /// Local NED velocity, m/s.
    pub velocity: [f64; 3],
}

impl PoseRecord {
    pub fn position(&self) -> Vec3 {
        Vec3::from(self.position)
    }

    pub fn gimbal(&self) -> GimbalAngles {
        GimbalAngles::from_degrees(self.gimbal_deg[0], self.gimbal_deg[1], self.gimbal_deg[2])
    }

    /// Camera pose with the given chain and gimbal frame.
    pub fn camera_pose(&self, chain: GimbalChain, frame: GimbalFrame) -> mavloc_geometry::CameraPose {
        use mavloc_geometry::{body_rotation, CameraPose, Mount};
        let a = self.attitude_deg.map(f64::to_radians);
        let mount = match frame {
            GimbalFrame::Earth => Mount::Earth,
            GimbalFrame::Body => Mount::Body { attitude: body_rotation(a[0], a[1], a[2]) },
        };
        CameraPose::from_gimbal(self.position(), chain, self.gimbal(), mount)
    }

    fn from_state(s: &State) -> PoseRecord {
        PoseRecord {
            position: s.position.into(),
            attitude_deg: s.attitude.map(f64::to_degrees),
            gimbal_deg: [s.gimbal.yaw.to_degrees(), s.gimbal.pitch.to_degrees(), s.gimbal.roll.to_degrees()],
            velocity: s.velocity.into(),
        }
    }
}

/// One line of `telemetry.jsonl`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TelemetryRecord {
    /// Frame index; the files are `frames/{frame:06}.png` and `masks/{frame:06}.png`.
    pub frame: u64,
    /// Capture time, seconds from the start of the flight.
    pub t: f64,
    /// The true pose (ground truth).
    #[serde(rename = "true")]
    pub truth: PoseRecord,
    /// The pose as the vehicle reported it: noise, offsets and gimbal lag applied.
    pub measured: PoseRecord,
    /// Photometric change applied to the frame, when there was one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance: Option<crate::views::Appearance>,
}

/// `camera.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraFile {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub chain: GimbalChain,
    pub gimbal_frame: GimbalFrame,
    /// WGS84 origin of the local NED frame.
    pub origin: mavloc_geometry::Geodetic,
}

impl CameraFile {
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        }
    }
}

/// Rendering choices that may differ from the scenario file.
#[derive(Clone, Debug, Default)]
pub struct RenderOptions {
    /// At most this many frames (default: one lap).
    pub frames: Option<usize>,
    /// Resolution override, keeping the field of view.
    pub size: Option<(u32, u32)>,
    pub seed: Option<u64>,
    pub noise: Option<NoiseSpec>,
    /// Overwrite a non-empty output folder.
    pub force: bool,
    /// Render this many random labelled views (indoor seed sec. 3.4.2) instead of the
    /// mission's flight. Indoor scenarios only.
    pub views: Option<usize>,
    /// Photometric change for every frame of a flight (brightness, contrast, blur).
    pub appearance: Option<crate::views::Appearance>,
}

/// What a render produced.
#[derive(Clone, Debug)]
pub struct RenderSummary {
    pub frames: usize,
    pub dropped: usize,
    pub dir: PathBuf,
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let tmp = path.with_extension("tmp");
    let io = |e: std::io::Error| format!("cannot write {}: {e}", path.display());
    let mut f = fs::File::create(&tmp).map_err(io)?;
    f.write_all(bytes).map_err(io)?;
    f.sync_all().map_err(io)?;
    fs::rename(&tmp, path).map_err(io)
}

fn write_png(path: &Path, width: u32, height: u32, data: &[u8], colour: bool) -> Result<(), String> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let mut buf = Vec::new();
    let kind = if colour { image::ExtendedColorType::Rgb8 } else { image::ExtendedColorType::L8 };
    PngEncoder::new_with_quality(&mut buf, CompressionType::Fast, FilterType::Sub)
        .write_image(data, width, height, kind)
        .map_err(|e| format!("cannot encode {}: {e}", path.display()))?;
    write_atomic(path, &buf)
}

/// Renders a scenario into a dataset folder. `progress(done, total)` is called after each
/// frame.
pub fn render_dataset(
    scenario: &Scenario,
    opts: &RenderOptions,
    out: &Path,
    mut progress: impl FnMut(usize, usize),
) -> Result<RenderSummary, String> {
    let mut scenario = scenario.clone();
    if let Some(seed) = opts.seed {
        scenario.seed = seed;
    }
    if let Some((w, h)) = opts.size {
        scenario.camera.width = w;
        scenario.camera.height = h;
    }
    if let Some(noise) = &opts.noise {
        scenario.noise = noise.clone();
    }
    scenario.validate()?;
    if out.exists() {
        let non_empty =
            fs::read_dir(out).map_err(|e| format!("cannot read {}: {e}", out.display()))?.next().is_some();
        if non_empty && !opts.force {
            return Err(format!("{} is not empty; pass --force to overwrite it", out.display()));
        }
    }
    for sub in ["frames", "masks"] {
        fs::create_dir_all(out.join(sub))
            .map_err(|e| format!("cannot create {}: {e}", out.join(sub).display()))?;
    }
    let _ = fs::remove_file(out.join("telemetry.jsonl"));

    let world = World::build(&scenario)?;
    let mission = Mission::plan(&world)?;
    let renderer = Renderer::new(&world);
    let k = scenario.intrinsics();

    // Static files first; telemetry last marks completeness.
    let camera = CameraFile {
        width: k.width,
        height: k.height,
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        chain: scenario.camera.chain,
        gimbal_frame: mission.gimbal_frame,
        origin: scenario.origin,
    };
    write_atomic(&out.join("camera.toml"), toml::to_string(&camera).map_err(|e| e.to_string())?.as_bytes())?;
    write_atomic(
        &out.join("scenario.toml"),
        toml::to_string(&scenario).map_err(|e| e.to_string())?.as_bytes(),
    )?;
    write_ground_truth(out, &world.frame, &world.ground_truth)?;
    let plan = serde_json::to_string_pretty(&mission.qgc_plan(&world.frame)).map_err(|e| e.to_string())?;
    write_atomic(&out.join("mission.plan"), plan.as_bytes())?;

    let noise = &scenario.noise;
    let mut rng = rand::rngs::StdRng::seed_from_u64(scenario.seed ^ 0x5eed);
    let unit = Normal::new(0.0, 1.0).map_err(|e| e.to_string())?;
    // What to render: the mission's flight, or random views.
    let shots: Vec<(State, Option<crate::views::Appearance>)> = match opts.views {
        Some(count) => {
            if mission.gimbal_frame != GimbalFrame::Body {
                return Err(format!("--views is for indoor scenarios; {} flies a mission", scenario.name));
            }
            let spec = scenario.views.clone().unwrap_or_default();
            crate::views::random_views(&spec, count, scenario.seed)
                .into_iter()
                .map(|(s, a)| (s, Some(a)))
                .collect()
        }
        None => {
            let total = opts.frames.unwrap_or(usize::MAX).min(mission.frame_count());
            (0..total).map(|i| (mission.state(i as f64 / mission.frame_rate), opts.appearance)).collect()
        }
    };
    let total = shots.len();
    let mut lines = String::new();
    let mut dropped = 0;
    let mut written = 0;
    for (i, (truth, appearance)) in shots.iter().enumerate() {
        if noise.drop_rate > 0.0 && rand::Rng::random::<f64>(&mut rng) < noise.drop_rate {
            dropped += 1;
            progress(i + 1, total);
            continue;
        }
        let mut frame = renderer.render(&mission.camera_pose(truth), &k);
        let appearance = appearance.filter(|a| !a.is_identity());
        if let Some(a) = appearance {
            a.apply(frame.width as usize, frame.height as usize, &mut frame.rgb);
        }
        let name = format!("{i:06}.png");
        write_png(&out.join("frames").join(&name), frame.width, frame.height, &frame.rgb, true)?;
        write_png(&out.join("masks").join(&name), frame.width, frame.height, &frame.mask, false)?;
        let measured = measure(&mission, truth, noise, opts.views.is_none(), &mut rng, &unit);
        let record = TelemetryRecord {
            frame: i as u64,
            t: truth.t,
            truth: PoseRecord::from_state(truth),
            measured,
            appearance,
        };
        lines.push_str(&serde_json::to_string(&record).map_err(|e| e.to_string())?);
        lines.push('\n');
        written += 1;
        progress(i + 1, total);
    }
    write_atomic(&out.join("telemetry.jsonl"), lines.as_bytes())?;
    Ok(RenderSummary { frames: written, dropped, dir: out.to_path_buf() })
}

/// What the vehicle reports for a true state: position noise, the gimbal attitude of
/// `gimbal_lag_s` earlier with static offsets and noise. Random views have no flight to
/// lag along (`on_flight` false).
fn measure(
    mission: &Mission,
    truth: &State,
    noise: &NoiseSpec,
    on_flight: bool,
    rng: &mut impl rand::Rng,
    unit: &Normal<f64>,
) -> PoseRecord {
    let mut sample = |sd: f64| if sd > 0.0 { sd * unit.sample(rng) } else { 0.0 };
    let lagged = if noise.gimbal_lag_s > 0.0 && on_flight {
        mission.state(truth.t - noise.gimbal_lag_s)
    } else {
        *truth
    };
    let mut r = PoseRecord::from_state(truth);
    for (c, sd) in r.position.iter_mut().zip(noise.position_sd_m) {
        *c += sample(sd);
    }
    let g = PoseRecord::from_state(&lagged).gimbal_deg;
    r.gimbal_deg = [
        g[0] + noise.gimbal_offset_deg[0] + sample(noise.gimbal_yaw_sd_deg),
        g[1] + noise.gimbal_offset_deg[1] + sample(noise.gimbal_pitch_sd_deg),
        g[2] + noise.gimbal_offset_deg[2],
    ];
    r
}

fn write_ground_truth(out: &Path, frame: &LocalFrame, lines: &[Vec<Vec3>]) -> Result<(), String> {
    let mut csv = String::from("line,index,north,east,down,lat,lon,alt\n");
    let mut features = Vec::new();
    for (li, line) in lines.iter().enumerate() {
        let mut coords = Vec::new();
        for (pi, p) in line.iter().enumerate() {
            let g = frame.to_geodetic(p);
            csv.push_str(&format!(
                "{li},{pi},{:.4},{:.4},{:.4},{:.9},{:.9},{:.4}\n",
                p.x, p.y, p.z, g.lat_deg, g.lon_deg, g.alt_m
            ));
            coords.push(vec![g.lon_deg, g.lat_deg, g.alt_m]);
        }
        let mut props = geojson::JsonObject::new();
        props.insert("name".into(), format!("ground truth border {li}").into());
        features.push(geojson::Feature {
            bbox: None,
            geometry: Some(geojson::Geometry::new_line_string(coords)),
            id: None,
            properties: Some(props),
            foreign_members: None,
        });
    }
    let fc = geojson::FeatureCollection { bbox: None, features, foreign_members: None };
    write_atomic(&out.join("ground_truth.csv"), csv.as_bytes())?;
    write_atomic(&out.join("ground_truth.geojson"), geojson::GeoJson::from(fc).to_string().as_bytes())
}

/// A dataset opened for reading.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub dir: PathBuf,
    pub camera: CameraFile,
    pub records: Vec<TelemetryRecord>,
    /// Ground-truth polylines, local NED.
    pub ground_truth: Vec<Vec<Vec3>>,
}

impl Dataset {
    /// Opens a dataset folder; every error names the file (and line) that is wrong.
    pub fn open(dir: &Path) -> Result<Dataset, String> {
        let read = |name: &str| {
            let p = dir.join(name);
            fs::read_to_string(&p).map_err(|e| format!("{}: {e}", p.display()))
        };
        let camera: CameraFile = toml::from_str(&read("camera.toml")?)
            .map_err(|e| format!("{}: {e}", dir.join("camera.toml").display()))?;
        camera.intrinsics().validate().map_err(|e| format!("{}: {e}", dir.join("camera.toml").display()))?;

        let tpath = dir.join("telemetry.jsonl");
        let f = fs::File::open(&tpath)
            .map_err(|e| format!("{}: {e} (an interrupted render leaves no telemetry)", tpath.display()))?;
        let mut records = Vec::new();
        for (n, line) in std::io::BufReader::new(f).lines().enumerate() {
            let line = line.map_err(|e| format!("{}: {e}", tpath.display()))?;
            if line.trim().is_empty() {
                continue;
            }
            let r: TelemetryRecord = serde_json::from_str(&line)
                .map_err(|e| format!("{} line {}: {e}", tpath.display(), n + 1))?;
            records.push(r);
        }

        let gpath = dir.join("ground_truth.csv");
        let mut ground_truth: Vec<Vec<Vec3>> = Vec::new();
        if gpath.exists() {
            for (n, line) in read("ground_truth.csv")?.lines().enumerate().skip(1) {
                let cols: Vec<&str> = line.split(',').collect();
                let bad =
                    || format!("{} line {}: expected line,index,north,east,down,...", gpath.display(), n + 1);
                if cols.len() < 5 {
                    return Err(bad());
                }
                let li: usize = cols[0].parse().map_err(|_| bad())?;
                let p: Vec<f64> = cols[2..5]
                    .iter()
                    .map(|c| c.parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| bad())?;
                while ground_truth.len() <= li {
                    ground_truth.push(Vec::new());
                }
                ground_truth[li].push(Vec3::new(p[0], p[1], p[2]));
            }
        }
        Ok(Dataset { dir: dir.to_path_buf(), camera, records, ground_truth })
    }

    /// `frames/NNNNNN.png`, or `.jpg` where the dataset holds photos (`mavloc import`).
    pub fn frame_path(&self, r: &TelemetryRecord) -> PathBuf {
        let png = self.dir.join("frames").join(format!("{:06}.png", r.frame));
        if png.exists() {
            return png;
        }
        let jpg = png.with_extension("jpg");
        if jpg.exists() {
            jpg
        } else {
            png
        }
    }

    pub fn mask_path(&self, r: &TelemetryRecord) -> PathBuf {
        self.dir.join("masks").join(format!("{:06}.png", r.frame))
    }
}
