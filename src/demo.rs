//! `make demo`: the whole loop, live, over UDP loopback. The simulated vehicle (with its
//! gimbal) flies, `mavloc run` with the sim camera localises, and this module only
//! orchestrates the two processes and measures what they left on disk:
//!
//! 1. coastline: the vehicle flies the shore for `coast_s` seconds, then lands; the
//!    area pipeline localises the shore live; landmarks are measured against the world's
//!    true shoreline (area seed ch. 6).
//! 2. indoor: a texton model is trained on rendered views of the floor; the vehicle flies
//!    its path over the floor; mavloc sends VISION_POSITION_ESTIMATE and, when the
//!    particles agree inside the landing zone, MAV_CMD_NAV_LAND; the vehicle lands. RMS
//!    error is measured against the vehicle's true track, and the touchdown against the
//!    zone.

use std::fmt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::area::eval::{evaluate, AreaEvaluation};
use crate::indoor::eval::{measure, IndoorEval};
use crate::output::{parse_landmarks_csv, plot};
use mavloc_data::results::{parse_border_csv, read_trajectory};
use mavloc_data::table::parse_lenient;
use mavloc_data::truth::TruthRow;

/// What to run.
#[derive(Clone, Debug)]
pub struct DemoOptions {
    /// The mavloc binary (the demo runs it as the vehicle and as the daemon).
    pub bin: PathBuf,
    pub out: PathBuf,
    /// Seconds of coastline flight before the vehicle lands.
    pub coast_s: f64,
    /// Longest indoor flight (the landing normally ends it sooner).
    pub indoor_s: f64,
    /// Views rendered to train the indoor model.
    pub views: usize,
}

impl Default for DemoOptions {
    fn default() -> Self {
        DemoOptions {
            bin: PathBuf::from("mavloc"),
            out: PathBuf::from("out/demo"),
            coast_s: 90.0,
            indoor_s: 60.0,
            views: 1000,
        }
    }
}

/// The daemon's counters from `status.json`.
#[derive(Clone, Debug, Default)]
pub struct Frames {
    pub processed: u64,
    pub dropped: u64,
}

#[derive(Clone, Debug)]
pub struct CoastResult {
    pub frames: Frames,
    /// The live run's `summary.json` (stage times per frame).
    pub summary: Option<crate::area::offline::RunSummary>,
    pub eval: AreaEvaluation,
    pub daemon_ok: bool,
}

#[derive(Clone, Debug)]
pub struct IndoorResult {
    pub frames: Frames,
    pub eval: IndoorEval,
    pub triggered: bool,
    /// Touchdown distance from the zone centre, metres (None: it never landed).
    pub touchdown_m: Option<f64>,
    pub zone_radius_m: f64,
    pub daemon_ok: bool,
}

/// The demo's report.
#[derive(Clone, Debug)]
pub struct DemoReport {
    pub coast: CoastResult,
    pub indoor: IndoorResult,
    pub out: PathBuf,
    pub elapsed_s: f64,
}

impl DemoReport {
    /// The demo's acceptance: coastline landmarks converged, none beyond 20 m, mean within
    /// 3 m (the seed reached 2.82 m); indoor RMS within 0.3 m once localised (after the
    /// first 2 s of global localisation from a uniform start), the trigger fired and the
    /// vehicle came down inside the zone; both daemons exited cleanly.
    pub fn passed(&self) -> bool {
        let c = &self.coast;
        let i = &self.indoor;
        c.daemon_ok
            && i.daemon_ok
            && c.eval.landmarks > 0
            && c.eval.gt20 == 0
            && c.eval.mean_m <= 3.0
            && i.eval.frames > 0
            && i.eval.rmse_after_2s_m <= 0.3
            && i.triggered
            && i.touchdown_m.is_some_and(|d| d <= i.zone_radius_m)
    }
}

impl fmt::Display for DemoReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = &self.coast;
        let i = &self.indoor;
        writeln!(f, "mavloc demo: simulated vehicle + mavloc run (sim camera), MAVLink over UDP loopback")?;
        writeln!(f, "  coastline (area pipeline, seed noise: gimbal 0.5 deg, position 0.5/0.5/2 m):")?;
        writeln!(f, "    frames processed {}, dropped {}", c.frames.processed, c.frames.dropped)?;
        if let Some(s) = &c.summary {
            writeln!(
                f,
                "    per frame: prepare {:.1} ms, band {:.1} ms, SIFT {:.1} ms, match+estimate {:.1} ms, purge+add {:.1} ms",
                s.prepare_ms, s.band_ms, s.sift_ms, s.match_estimate_ms, s.purge_add_ms
            )?;
        }
        writeln!(
            f,
            "    landmarks {}, >20 m {}, mean distance to the true shore {:.2} m (median {:.2}, max {:.2}); border line mean {:.2} m",
            c.eval.landmarks, c.eval.gt20, c.eval.mean_m, c.eval.median_m, c.eval.max_m, c.eval.border_mean_m
        )?;
        writeln!(f, "  indoor floor (texton pipeline, landing trigger):")?;
        writeln!(f, "    frames processed {}, dropped {}", i.frames.processed, i.frames.dropped)?;
        writeln!(
            f,
            "    RMS error in flight {:.3} m over {} frames ({:.3} m after the first 2 s)",
            i.eval.rmse_m, i.eval.frames, i.eval.rmse_after_2s_m
        )?;
        match i.touchdown_m {
            Some(d) => writeln!(
                f,
                "    landing {}: touchdown {d:.2} m from the zone centre ({} the {:.1} m zone)",
                if i.triggered { "triggered by mavloc" } else { "NOT triggered (vehicle timed out)" },
                if d <= i.zone_radius_m { "inside" } else { "OUTSIDE" },
                i.zone_radius_m
            )?,
            None => writeln!(f, "    no landing")?,
        }
        writeln!(f, "  files and plots: {}", self.out.display())?;
        writeln!(
            f,
            "    coastline/state/results/area/ (landmarks.csv, area.kml, area.geojson, histogram.png, views.png)"
        )?;
        writeln!(
            f,
            "    indoor/state/results/indoor/ (trajectory.csv, trajectory.png); logs in */mavloc.log"
        )?;
        writeln!(f, "  time {:.1} s; result {}", self.elapsed_s, if self.passed() { "PASS" } else { "FAIL" })
    }
}

/// The child gets SIGTERM when the demo dies, so a killed demo leaves no vehicle or
/// daemon behind.
fn die_with_parent(cmd: &mut Command) -> &mut Command {
    use std::os::unix::process::CommandExt;
    // SAFETY: prctl is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
            Ok(())
        })
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// The vehicle and the daemon of one flight.
struct Flight {
    vehicle: Child,
    daemon: Child,
    dir: PathBuf,
}

impl Flight {
    fn start(
        bin: &Path,
        dir: &Path,
        scenario: &str,
        seconds: f64,
        sets: &[String],
    ) -> anyhow::Result<Flight> {
        std::fs::create_dir_all(dir)?;
        let port = free_port()?;
        let log = std::fs::File::create(dir.join("mavloc.log"))?;
        let mut daemon = Command::new(bin);
        daemon
            .args(["run", "--mavlink", &format!("udpin:127.0.0.1:{port}")])
            .args(["--set", &format!("daemon.state_dir={}", dir.join("state").display())])
            .args(["--set", "camera.source=sim", "--set", &format!("camera.scenario={scenario}")]);
        for s in sets {
            daemon.args(["--set", s]);
        }
        let daemon = die_with_parent(&mut daemon)
            .env("RUST_LOG", "mavloc=info")
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()?;
        let vlog = std::fs::File::create(dir.join("vehicle.log"))?;
        let vehicle = die_with_parent(&mut Command::new(bin))
            .args([
                "sim",
                "vehicle",
                "--scenario",
                scenario,
                "--mavlink",
                &format!("udpout:127.0.0.1:{port}"),
            ])
            .args(["--duration", &seconds.to_string()])
            .arg("--truth-log")
            .arg(dir.join("truth.csv"))
            .stdout(vlog.try_clone()?)
            .stderr(vlog)
            .stdin(Stdio::null())
            .spawn()?;
        Ok(Flight { vehicle, daemon, dir: dir.to_path_buf() })
    }

    /// Waits for the vehicle to land and exit (at most `limit`), then stops the daemon
    /// with SIGTERM; true when the daemon exited 0.
    fn finish(mut self, limit: Duration) -> anyhow::Result<bool> {
        let start = Instant::now();
        while self.vehicle.try_wait()?.is_none() {
            if start.elapsed() > limit {
                let _ = self.vehicle.kill();
                tracing::warn!("the simulated vehicle did not land within {limit:?}");
                break;
            }
            if let Some(s) = self.daemon.try_wait()? {
                let _ = self.vehicle.kill();
                anyhow::bail!("mavloc run exited early ({s}); see {}", self.dir.join("mavloc.log").display());
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        let _ = self.vehicle.wait();
        // SAFETY: kill(2) on our own child.
        unsafe { libc::kill(self.daemon.id() as i32, libc::SIGTERM) };
        let t = Instant::now();
        loop {
            if let Some(s) = self.daemon.try_wait()? {
                return Ok(s.success());
            }
            if t.elapsed() > Duration::from_secs(5) {
                let _ = self.daemon.kill();
                return Ok(false);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

fn frames(state: &Path) -> Frames {
    let v: serde_json::Value = std::fs::read_to_string(state.join("status.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default();
    Frames {
        processed: v["counters"]["frames_processed"].as_u64().unwrap_or(0),
        dropped: v["counters"]["frames_dropped"].as_u64().unwrap_or(0),
    }
}

fn coastline(opts: &DemoOptions, progress: &mut impl FnMut(&str)) -> anyhow::Result<CoastResult> {
    let dir = opts.out.join("coastline");
    let _ = std::fs::remove_dir_all(&dir);
    progress(&format!("coastline: flying {:.0} s with the area pipeline live", opts.coast_s));
    // 960x540 at 15 frames/s, the band kept at the seed's 50 px of a full-HD frame.
    let sets: Vec<String> =
        ["camera.width=960", "camera.height=540", "camera.fps=15", "area.downscale=1", "area.band_px=25"]
            .iter()
            .map(|s| s.to_string())
            .collect();
    let flight = Flight::start(&opts.bin, &dir, "coastline", opts.coast_s, &sets)?;
    let daemon_ok = flight.finish(Duration::from_secs_f64(opts.coast_s + 60.0))?;
    // A link to the run's last complete set, written when the daemon stopped: the plots
    // join that set, which stays (only a run's older sets are removed).
    let results = dir.join("state/results/area");
    let lpath = results.join("landmarks.csv");
    let landmarks = parse_landmarks_csv(&std::fs::read_to_string(&lpath)?, &lpath.display().to_string())
        .map_err(anyhow::Error::msg)?;
    let border = parse_border_csv(&std::fs::read_to_string(results.join("border.csv")).unwrap_or_default());
    let world =
        mavloc_sim::World::build(&mavloc_sim::Scenario::load("coastline").map_err(anyhow::Error::msg)?)
            .map_err(anyhow::Error::msg)?;
    let eval = evaluate(&landmarks, &world.ground_truth, &border, 6.0);
    let points: Vec<_> = landmarks.iter().map(|l| l.position).collect();
    let title = "mavloc demo: coastline, live";
    plot::distance_histogram(&results.join("histogram.png"), &eval.distances, title)
        .map_err(anyhow::Error::msg)?;
    plot::landmark_views(&results.join("views.png"), &points, &world.ground_truth, &border, title)
        .map_err(anyhow::Error::msg)?;
    let summary = std::fs::read_to_string(results.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok());
    Ok(CoastResult { frames: frames(&dir.join("state")), summary, eval, daemon_ok })
}

fn indoor(opts: &DemoOptions, progress: &mut impl FnMut(&str)) -> anyhow::Result<IndoorResult> {
    let dir = opts.out.join("indoor");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    progress(&format!("indoor: rendering {} views of the floor and training a texton model", opts.views));
    let views = dir.join("views");
    let run = |args: &[&str], what: &str| -> anyhow::Result<()> {
        let out = Command::new(&opts.bin).args(args).output()?;
        anyhow::ensure!(out.status.success(), "{what} failed: {}", String::from_utf8_lossy(&out.stderr));
        Ok(())
    };
    let (v, vs) = (views.display().to_string(), opts.views.to_string());
    run(
        &[
            "sim",
            "render",
            "--scenario",
            "indoor-floor",
            "--views",
            &vs,
            "--width",
            "320",
            "--height",
            "240",
            "--out",
            &v,
        ],
        "rendering views",
    )?;
    let model = dir.join("floor.model");
    let m = model.display().to_string();
    run(&["indoor", "train", "--dataset", &v, "--out", &m], "training")?;

    // The zone: where the vehicle's path is 20 s into the flight.
    let world =
        mavloc_sim::World::build(&mavloc_sim::Scenario::load("indoor-floor").map_err(anyhow::Error::msg)?)
            .map_err(anyhow::Error::msg)?;
    let zone = mavloc_sim::Mission::plan(&world).map_err(anyhow::Error::msg)?.state(20.0).position;
    let radius = 0.6;
    progress(&format!(
        "indoor: flying with the texton pipeline live; landing zone at x {:.2} y {:.2} m, radius {radius} m",
        zone.x, zone.y
    ));
    let sets = vec![
        "daemon.pipeline=indoor".into(),
        format!("indoor.model={m}"),
        "camera.width=320".into(),
        "camera.height=240".into(),
        "camera.fps=15".into(),
        "indoor.landing_enabled=true".into(),
        format!("indoor.landing_x_m={}", zone.x),
        format!("indoor.landing_y_m={}", zone.y),
        format!("indoor.landing_radius_m={radius}"),
    ];
    let flight = Flight::start(&opts.bin, &dir, "indoor-floor", opts.indoor_s, &sets)?;
    let daemon_ok = flight.finish(Duration::from_secs_f64(opts.indoor_s + 60.0))?;

    // The true track (vehicle time) and the estimates (stamped with the same clock).
    // Lenient, as before: a line the vehicle was stopped in the middle of is skipped.
    let truth: Vec<TruthRow> = parse_lenient(&std::fs::read_to_string(dir.join("truth.csv"))?);
    let landing_t = truth.iter().find(|r| r.phase != "Mission").map(|r| r.t).unwrap_or(f64::INFINITY);
    let touchdown_m = truth
        .iter()
        .rev()
        .find(|r| r.phase == "Landed")
        .map(|r| ((r.north - zone.x).powi(2) + (r.east - zone.y).powi(2)).sqrt());
    let results = dir.join("state/results/indoor");
    let rows = read_trajectory(&results.join("trajectory.csv")).map_err(anyhow::Error::msg)?;
    let flying: Vec<_> = rows.into_iter().filter(|r| r.t < landing_t).collect();
    let est: Vec<(f64, f64, f64)> = flying.iter().map(|r| (r.t, r.x, r.y)).collect();
    let tru: Vec<(f64, f64)> = flying.iter().map(|r| (r.true_x, r.true_y)).collect();
    let mut eval = measure(&est, &tru);
    let fix: Vec<bool> = flying.iter().map(|r| r.fix).collect();
    crate::indoor::eval::measure_fixes(&mut eval, &est, &tru, &fix);
    if let (Some(a), Some(b)) = (flying.first(), flying.last()) {
        eval.frames_per_s = flying.len() as f64 / (b.t - a.t).max(1e-9);
    }
    crate::indoor::eval::plot(&results.join("trajectory.png"), &flying, "mavloc demo: indoor floor, live")
        .map_err(anyhow::Error::msg)?;
    let log = std::fs::read_to_string(dir.join("mavloc.log")).unwrap_or_default();
    Ok(IndoorResult {
        frames: frames(&dir.join("state")),
        eval,
        triggered: log.contains("landing requested"),
        touchdown_m,
        zone_radius_m: radius,
        daemon_ok,
    })
}

/// Runs the demo. `progress(stage)` is told what is happening.
pub fn run(opts: &DemoOptions, mut progress: impl FnMut(&str)) -> anyhow::Result<DemoReport> {
    let start = Instant::now();
    std::fs::create_dir_all(&opts.out)?;
    let coast = coastline(opts, &mut progress)?;
    let indoor = indoor(opts, &mut progress)?;
    Ok(DemoReport { coast, indoor, out: opts.out.clone(), elapsed_s: start.elapsed().as_secs_f64() })
}
