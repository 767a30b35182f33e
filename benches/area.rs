//! Where the area pipeline's time goes, per stage, at the working resolution (960x540,
//! band 25 px, L_max 200): band (distance transform vs the seed's dilation), SIFT in the
//! band, match-and-estimate against a full library, the UKF updates alone, purge, and a
//! whole frame at steady state. Frames come from the coastline mission. Beside them, the
//! water segmenter on a real photo and its shadow check alone, and reading a rendered
//! frame's PNG through mavloc's reader against OpenCV's.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use mavloc::area::features::{prepare, FeatureExtractor, Pieces};
use mavloc::area::library::{Landmark, LibraryParams};
use mavloc::area::{AreaPipeline, FrameInput};
use mavloc::filter::{bearing_noise, BearingModel, Ukf, UkfParams};
use mavloc::geometry::{bearing_between, CameraPose, Vec3};
use mavloc::settings::Settings;
use mavloc_sim::{Mission, Renderer, Scenario, World};
use nalgebra::{Matrix3, Vector2};
use opencv::core::Mat;
use opencv::prelude::*;

/// The bundle adjustment benches' data: recorded attitudes, ground points and the
/// filters' starting tracks, drawn in that order from the caller's generator.
mod refine_data {
    use mavloc::area::refine::corrected;
    use mavloc::geometry::{CameraPose, Vec3};
    use mavloc_data::results::LandmarkRecord;
    use rand::rngs::StdRng;
    use rand::Rng;
    use std::collections::BTreeMap;
    use std::ops::Range;

    fn unit(rng: &mut StdRng) -> Vec3 {
        Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0))
            .normalize()
    }

    /// Each pose turned `deg` degrees about an axis of its own.
    pub fn tagged(
        truth: &BTreeMap<u64, CameraPose>,
        rng: &mut StdRng,
        deg: f64,
    ) -> BTreeMap<u64, CameraPose> {
        truth.iter().map(|(&f, p)| (f, corrected(p, &(unit(rng) * deg.to_radians())))).collect()
    }

    /// `n` points over `x` by `y`, within 2 m of the ground plane.
    pub fn points(rng: &mut StdRng, n: usize, x: Range<f64>, y: Range<f64>) -> Vec<Vec3> {
        (0..n)
            .map(|_| {
                Vec3::new(
                    rng.random_range(x.clone()),
                    rng.random_range(y.clone()),
                    rng.random_range(-2.0..2.0),
                )
            })
            .collect()
    }

    /// A track per point, starting `m` metres off it in a direction of its own.
    pub fn tracks_off(points: &[Vec3], rng: &mut StdRng, m: f64) -> Vec<LandmarkRecord> {
        points
            .iter()
            .enumerate()
            .map(|(j, x)| LandmarkRecord {
                id: j as u64,
                position: x + unit(rng) * m,
                sigma_max_m: 0.5,
                observations: 3,
                first_frame: 0,
                last_frame: 0,
            })
            .collect()
    }
}

struct Frame {
    grey: Mat,
    mask: Mat,
    pose: CameraPose,
}

fn frames(count: usize) -> (Vec<Frame>, mavloc::geometry::Intrinsics) {
    let scenario = Scenario::load("coastline").unwrap();
    let world = World::build(&scenario).unwrap();
    let mission = Mission::plan(&world).unwrap();
    let renderer = Renderer::new(&world);
    let k = scenario.intrinsics().downscaled(2);
    let out = (0..count)
        .map(|i| {
            let state = mission.state(20.0 + i as f64 / mission.frame_rate);
            let pose = mission.camera_pose(&state);
            let f = renderer.render(&pose, &k);
            let rgb =
                Mat::from_slice(&f.rgb).unwrap().reshape(3, f.height as i32).unwrap().try_clone().unwrap();
            let mut bgr = Mat::default();
            opencv::imgproc::cvt_color(&rgb, &mut bgr, opencv::imgproc::COLOR_RGB2BGR, 0).unwrap();
            let mask =
                Mat::from_slice(&f.mask).unwrap().reshape(1, f.height as i32).unwrap().try_clone().unwrap();
            let (grey, mask) = prepare(&bgr, &mask, 1).unwrap();
            Frame { grey, mask, pose }
        })
        .collect();
    (out, k)
}

/// One coastline frame at the working resolution as the simulator writes it (fast
/// deflate, Sub filter).
fn png_frame() -> Vec<u8> {
    let scenario = Scenario::load("coastline").unwrap();
    let world = World::build(&scenario).unwrap();
    let mission = Mission::plan(&world).unwrap();
    let k = scenario.intrinsics().downscaled(2);
    let f = Renderer::new(&world).render(&mission.camera_pose(&mission.state(20.0)), &k);
    mavloc_data::pngfile::encode(f.width, f.height, &f.rgb, mavloc_data::pngfile::Channels::Rgb).unwrap()
}

fn stages(c: &mut Criterion) {
    let s = Settings::default();
    {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        std::fs::write(&path, png_frame()).unwrap();
        let colour = opencv::imgcodecs::IMREAD_COLOR;
        c.bench_function("area_read_frame_png_960x540", |b| {
            b.iter(|| mavloc::imaging::read_image(&path, colour).unwrap())
        });
        c.bench_function("area_read_frame_png_960x540_opencv", |b| {
            b.iter(|| {
                let bytes = opencv::core::Vector::<u8>::from_slice(&std::fs::read(&path).unwrap());
                opencv::imgcodecs::imdecode(&bytes, colour).unwrap()
            })
        });
    }
    let (frames, k) = frames(40);
    let band_px = (s.area.band_px / s.area.downscale) as i32;
    let mut ex =
        FeatureExtractor::new(s.area.l_max as i32, (s.area.l_max * s.area.feature_factor) as i32, band_px)
            .unwrap();
    let f0 = &frames[0];
    c.bench_function("area_band_distance_transform", |b| b.iter(|| ex.band(&f0.mask).unwrap()));
    c.bench_function("area_band_dilation_seed", |b| b.iter(|| ex.band_by_dilation(&f0.mask).unwrap()));
    let band = ex.band(&f0.mask).unwrap();
    c.bench_function("area_sift_in_band_2000", |b| b.iter(|| ex.extract(&f0.grey, &band, false).unwrap()));
    // The same frame with SIFT over the band's whole bounding box (before the pieces).
    c.bench_function("area_sift_in_band_one_box", |b| {
        b.iter(|| ex.extract_in(&f0.grey, &band, false, Pieces::OneBox).unwrap())
    });

    // A library at steady state: run the pipeline over the first 39 frames.
    let mut pipeline = AreaPipeline::new(&s.area, k).unwrap();
    for (i, f) in frames.iter().take(39).enumerate() {
        pipeline
            .process(&FrameInput { index: i as u64, grey: &f.grey, mask: &f.mask, pose: f.pose })
            .unwrap();
    }
    let last = &frames[39];
    c.bench_function("area_whole_frame_steady_state", |b| {
        b.iter(|| {
            pipeline
                .process(&FrameInput { index: 39, grey: &last.grey, mask: &last.mask, pose: last.pose })
                .unwrap()
        })
    });

    // UKF updates of a full library (200 landmarks), without matching.
    let truth: Vec<Vec3> =
        (0..200).map(|i| Vec3::new(60.0 + (i % 20) as f64, (i / 20) as f64 * 3.0, 0.0)).collect();
    let observer = Vec3::new(0.0, 0.0, -30.0);
    let r = bearing_noise(0.5f64.to_radians());
    let filters: Vec<Ukf<3>> = truth
        .iter()
        .map(|t| {
            Ukf::new(t + Vec3::new(3.0, -2.0, 1.0), Matrix3::identity() * 25.0, UkfParams::default()).unwrap()
        })
        .collect();
    // The same updates in the three ways the library can make them: the seed's local
    // yaw/pitch, bearings about the measured ray (what the library does), and that with
    // five iterations (the photo-survey setting).
    let mut group = c.benchmark_group("area_ukf_update_200_landmarks");
    group.bench_function("local_yaw_pitch", |b| {
        b.iter_batched(
            || filters.clone(),
            |mut fs| {
                for (f, t) in fs.iter_mut().zip(&truth) {
                    let bt = bearing_between(&observer, t).unwrap();
                    let _ = f.update(&BearingModel::new(observer), &Vector2::new(bt.yaw, bt.pitch), &r);
                }
                fs
            },
            BatchSize::SmallInput,
        )
    });
    for iterations in [1, 5] {
        let name = format!("about_ray_{iterations}_iterations");
        group.bench_function(name, |b| {
            b.iter_batched(
                || filters.clone(),
                |mut fs| {
                    for (f, t) in fs.iter_mut().zip(&truth) {
                        let model = BearingModel::about(observer, &(t - observer));
                        if let Ok(pred) = f.predict_measurement(&model, &r) {
                            let _ = f.update_iterated(&model, &pred, &BearingModel::ZERO, &r, iterations);
                        }
                    }
                    fs
                },
                BatchSize::SmallInput,
            )
        });
    }
    group.finish();

    // Segmenting a real photo (DJI_0030, 4000x2250) with the water rule, and the rule's
    // shadow check (`area::shadow`) alone at the rule's 800 px working width: the check's
    // share of the segmenter.
    let photo_path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/dji-sample/DJI_0030.JPG");
    let photo = opencv::imgcodecs::imread(photo_path, opencv::imgcodecs::IMREAD_COLOR).unwrap();
    let water = mavloc::settings::Area { segmenter: mavloc::settings::Segmenter::Water, ..s.area.clone() };
    c.bench_function("area_segment_water_4000px_photo", |b| {
        b.iter(|| mavloc::area::segment::segment(&photo, &water).unwrap())
    });
    let small = mavloc::area::segment::shrunk(&photo).unwrap();
    c.bench_function("area_shadow_check_800px", |b| {
        b.iter(|| mavloc::area::shadow::cast_shadows(&small).unwrap())
    });

    // Matching two photos for the alignment (`area::align`, 4000 SIFT keypoints at 1600
    // px, DJI_0030 and DJI_0031): FLANN's trees built for the pair and queried once, the
    // trees alone, and a query against trees built beforehand
    // (`FlannIndex`, built once per photo for all its pairs); exhaustive matching beside.
    {
        use mavloc::area::imageup::{features_sized, matched, FlannIndex};
        let read = |name: &str| {
            let path = format!("{}/tests/data/dji-sample/{name}", env!("CARGO_MANIFEST_DIR"));
            let img = opencv::imgcodecs::imread(&path, opencv::imgcodecs::IMREAD_COLOR).unwrap();
            features_sized(&img, 4000, 1600.0).unwrap()
        };
        let (a, b) = (read("DJI_0030.JPG"), read("DJI_0031.JPG"));
        c.bench_function("area_align_match_flann_per_pair", |bench| {
            bench.iter(|| FlannIndex::new(&b).unwrap().matched(&a).unwrap())
        });
        c.bench_function("area_align_match_flann_build_trees", |bench| {
            bench.iter(|| FlannIndex::new(&b).unwrap())
        });
        let mut index = FlannIndex::new(&b).unwrap();
        c.bench_function("area_align_match_flann_query_built_trees", |bench| {
            bench.iter(|| index.matched(&a).unwrap())
        });
        c.bench_function("area_align_match_exhaustive", |bench| bench.iter(|| matched(&a, &b).unwrap()));
    }

    // The photo runs' bundle adjustment (`area::refine`, which `area::align` runs twice on
    // the tie points): 18 nadir photos in three lines of six at 70 m, 4000 tie points over
    // their ground, each photo's attitude 2 deg off and every track starting 2 m off.
    {
        use mavloc::area::refine::{refine, RefineParams};
        use mavloc::geometry::{GimbalAngles, GimbalChain, Intrinsics, Mount, Pixel};
        use rand::SeedableRng;
        use std::collections::BTreeMap;
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let k = Intrinsics { width: 1600, height: 900, fx: 1300.0, fy: 1300.0, cx: 799.5, cy: 449.5 };
        let truth: BTreeMap<u64, CameraPose> = (0..18u64)
            .map(|i| {
                let (line, along) = ((i / 6) as f64, (i % 6) as f64);
                let angles = GimbalAngles { yaw: 0.0, pitch: -89f64.to_radians(), roll: 0.0 };
                let position = Vec3::new(along * 25.0, line * 45.0, -70.0);
                (i, CameraPose::from_gimbal(position, GimbalChain::YawPitchRoll, angles, Mount::Earth))
            })
            .collect();
        let tagged = refine_data::tagged(&truth, &mut rng, 2.0);
        let points = refine_data::points(&mut rng, 4000, -40.0..165.0, -30.0..120.0);
        let mut sightings: Vec<(u64, u64, Pixel)> = Vec::new();
        for (&f, p) in &truth {
            for (j, x) in points.iter().enumerate() {
                if let Some(px) = p.project(&k, x).filter(|px| k.contains(*px)) {
                    sightings.push((f, j as u64, px));
                }
            }
        }
        let start = refine_data::tracks_off(&points, &mut rng, 2.0);
        let params = RefineParams::new(2.0);
        c.bench_function("area_refine_18_photos_4000_tracks", |b| {
            b.iter(|| refine(&sightings, &start, &tagged, &k, &params))
        });
    }

    // The same adjustment over a video flight (what `mavloc area --trace` runs on a
    // recorded PX4 flight of 1874 frames): 600 frames a metre apart along a line at 60 m,
    // the camera 30 deg off nadir, each frame's attitude 1 deg off, 1500 tracks each seen
    // by the 40-90 frames that pass over it: a banded reduced system of 600 blocks.
    {
        use mavloc::area::refine::{refine, RefineParams};
        use mavloc::geometry::{GimbalAngles, GimbalChain, Intrinsics, Mount, Pixel};
        use rand::SeedableRng;
        use std::collections::BTreeMap;
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let k = Intrinsics { width: 640, height: 360, fx: 420.0, fy: 420.0, cx: 319.5, cy: 179.5 };
        let truth: BTreeMap<u64, CameraPose> = (0..600u64)
            .map(|i| {
                let angles = GimbalAngles { yaw: 0.0, pitch: -60f64.to_radians(), roll: 0.0 };
                let position = Vec3::new(i as f64, 0.0, -60.0);
                (i, CameraPose::from_gimbal(position, GimbalChain::YawPitchRoll, angles, Mount::Earth))
            })
            .collect();
        let tagged = refine_data::tagged(&truth, &mut rng, 1.0);
        let points = refine_data::points(&mut rng, 1500, 30.0..700.0, -30.0..30.0);
        // A track lives while its point is in view, up to 90 frames (the library's turnover).
        let mut sightings: Vec<(u64, u64, Pixel)> = Vec::new();
        for (j, x) in points.iter().enumerate() {
            let seen = truth
                .iter()
                .filter_map(|(&f, p)| p.project(&k, x).filter(|px| k.contains(*px)).map(|px| (f, px)));
            sightings.extend(seen.take(90).map(|(f, px)| (f, j as u64, px)));
        }
        let start = refine_data::tracks_off(&points, &mut rng, 1.0);
        let params = RefineParams::new(1.5);
        let mut group = c.benchmark_group("area_refine_video");
        group.sample_size(10);
        group.bench_function("area_refine_video_600_frames_1500_tracks", |b| {
            b.iter(|| refine(&sightings, &start, &tagged, &k, &params))
        });
        group.finish();
    }

    // Purge 20 of 220 landmarks.
    let descriptor = vec![0.5f32; 128];
    c.bench_function("area_purge_220_to_180", |b| {
        b.iter_batched(
            || {
                let mut lib =
                    mavloc::area::library::Library::new(LibraryParams::from_settings(&s.area)).unwrap();
                for (i, f) in filters.iter().chain(filters.iter().take(20)).enumerate() {
                    let mut l = Landmark::new(f.clone(), &descriptor, (i % 50) as u64);
                    l.observations = (i % 7) as u32 + 1;
                    lib.push(l);
                }
                lib
            },
            |mut lib| lib.purge(60),
            BatchSize::SmallInput,
        )
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = stages
}
criterion_main!(benches);
