//! The indoor loop's stages (indoor seed sec. 3.3), on one core where the stage is serial:
//! preparing a frame (a whole canvas for training; 400 patches gathered for flight),
//! full-sampling and random-sampling histograms, the particle estimate (the seed's MAP
//! against the mode), k-NN (brute force against a kiddo k-d tree at 500 and 50 000 training
//! samples), systematic resampling against the seed's resampling wheel, the particle
//! filter step, and the whole per-frame loop of the target (400-sample histogram,
//! k-NN over 1000 samples, 100 and 500 particles), and the camera's velocity from two
//! frames (`indoor::flow`, beyond the seed). Frames come from the indoor-floor scenario.

use std::hint::black_box;
use std::num::NonZero;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use mavloc::filter::particle::{resampling_wheel, systematic, Gaussian2, ParticleFilter};
use mavloc::indoor::derotate::{Canvas, Preprocessor};
use mavloc::indoor::flow::{Flow, FlowFrame};
use mavloc::indoor::knn::Knn;
use mavloc::indoor::localizer::{Localizer, LocalizerParams};
use mavloc::indoor::model::{FrameParams, Model, TrainingInfo, MODEL_FORMAT, MODEL_VERSION};
use mavloc::indoor::textons::{Dictionary, Learning};
use mavloc::settings::MotionModel;
use mavloc_sim::{views, Mission, Renderer, Scenario, World};
use nalgebra::{Matrix2, Vector2};
use opencv::core::Mat;
use opencv::prelude::*;
use rand::{Rng, SeedableRng};

/// Rendered indoor views as BGR frames with their camera rotations.
fn frames(count: usize) -> (Vec<(Mat, mavloc::geometry::Rot3)>, mavloc::geometry::Intrinsics) {
    let scenario = Scenario::load("indoor-floor").unwrap();
    let world = World::build(&scenario).unwrap();
    let mission = Mission::plan(&world).unwrap();
    let renderer = Renderer::new(&world);
    let k = scenario.intrinsics();
    let spec = scenario.views.clone().unwrap_or_default();
    let out = views::random_views(&spec, count, 5)
        .into_iter()
        .map(|(state, _)| {
            let pose = mission.camera_pose(&state);
            let f = renderer.render(&pose, &k);
            let rgb =
                Mat::from_slice(&f.rgb).unwrap().reshape(3, f.height as i32).unwrap().try_clone().unwrap();
            let mut bgr = Mat::default();
            opencv::imgproc::cvt_color(&rgb, &mut bgr, opencv::imgproc::COLOR_RGB2BGR, 0).unwrap();
            (bgr, pose.local_from_camera())
        })
        .collect();
    (out, k)
}

fn dictionary(canvases: &[Canvas], n: usize) -> Dictionary {
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let patches: Vec<Vec<f32>> = canvases
        .iter()
        .flat_map(|c| Dictionary::sample_patches(&c.img, &c.mask, (6, 6), 500, &mut rng))
        .collect();
    Dictionary::learn_from_patches(&patches, n, 6, 6, Learning::Competitive { rate_millis: 20 }).unwrap()
}

/// A model of `count` random histograms over an 8 x 8 m map.
fn model(dictionary: Dictionary, count: usize) -> Model {
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    let n = dictionary.len();
    let histograms: Vec<Vec<f32>> = (0..count)
        .map(|_| {
            let h: Vec<f32> = (0..n).map(|_| rng.random::<f32>()).collect();
            let s: f32 = h.iter().sum();
            h.iter().map(|v| v / s).collect()
        })
        .collect();
    let positions = (0..count).map(|_| [rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0)]).collect();
    Model {
        format: MODEL_FORMAT.into(),
        version: MODEL_VERSION,
        frame: FrameParams {
            work_width: 320,
            work_fx: 228.0,
            derotate: true,
            normalise: true,
            height_ref_m: None,
        },
        dictionary,
        histograms,
        positions,
        measurement_cov: vec![[[0.04, 0.0], [0.0, 0.04]]; 5],
        inlier_fraction: vec![0.8, 0.6, 0.5, 0.4, 0.3],
        process_cov: [[0.0025, 0.0], [0.0, 0.0025]],
        bounds: [[-4.0, -4.0], [4.0, 4.0]],
        training: TrainingInfo {
            dataset: "bench".into(),
            labelling: "telemetry".into(),
            images: count,
            rejected: 0,
            process_source: "bench".into(),
            loo_rms_m: vec![],
        },
    }
}

fn stages(c: &mut Criterion) {
    let (frames, k) = frames(8);
    let pre = Preprocessor::new(k, 320, true, (6, 6));
    let canvases: Vec<Canvas> = frames.iter().map(|(f, r)| pre.prepare(f, Some(r), None).unwrap()).collect();
    let dict = dictionary(&canvases, 20);

    let mut g = c.benchmark_group("indoor_prepare");
    g.bench_function("whole canvas 640x480 (training)", |b| {
        b.iter(|| pre.prepare(black_box(&frames[0].0), Some(&frames[0].1), None).unwrap())
    });
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let mut patches = Vec::new();
    g.bench_function("sample 400 patches 640x480 (flight)", |b| {
        b.iter(|| {
            pre.sample(black_box(&frames[0].0), Some(&frames[0].1), None, 400, &mut rng, &mut patches)
                .unwrap()
        })
    });
    g.finish();

    // The camera's velocity (indoor::flow): a frame's grey copy and the two warps and the
    // DFT correlation against the frame before (the same frame twice here: the same work).
    let mut g = c.benchmark_group("indoor_flow");
    let flow = Flow::new().unwrap();
    // A view level enough for the whole path (a steep one returns early).
    let (f0, r0) = frames
        .iter()
        .find(|(f, r)| {
            let a = FlowFrame::new(0.0, f, *r, 1.0).unwrap();
            let b = FlowFrame::new(1.0 / 15.0, f, *r, 1.0).unwrap();
            flow.motion(&a, &b, &k).is_ok()
        })
        .expect("a level view among the rendered ones");
    let prev = FlowFrame::new(0.0, f0, *r0, 1.0).unwrap();
    g.bench_function("velocity from a 640x480 frame and the one before", |b| {
        b.iter(|| {
            let cur = FlowFrame::new(1.0 / 15.0, black_box(f0), *r0, 1.0).unwrap();
            black_box(flow.motion(&prev, &cur, &k))
        })
    });
    g.finish();

    let mut g = c.benchmark_group("indoor_histogram");
    g.sample_size(20);
    for n in [20usize, 64] {
        let d = if n == 20 { dict.clone() } else { dictionary(&canvases, n) };
        g.bench_function(BenchmarkId::new("full_sampling_one_core", n), |b| {
            b.iter(|| d.histogram_full_serial(black_box(&canvases[1].img), Some(&canvases[1].mask)))
        });
        // The same counts searched patch by patch in place (`Classifier::nearest`, what
        // full sampling did before it gathered rows for the flat kernel).
        let c = d.classifier();
        g.bench_function(BenchmarkId::new("full_sampling_one_core_per_patch", n), |b| {
            b.iter(|| {
                let (img, mask) = (black_box(&canvases[1].img), &canvases[1].mask);
                let mut counts = vec![0u64; d.len()];
                for y in 0..=img.height - d.h {
                    for x in 0..=img.width - d.w {
                        if mask.allows(x, y) {
                            counts[c.nearest(img, x, y)] += 1;
                        }
                    }
                }
                counts
            })
        });
        // The flight path: 400 patches gathered from a frame, classified (AVX2 and FMA
        // where the CPU has them).
        let classifier = d.classifier();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut patches = Vec::new();
        pre.sample(&frames[1].0, Some(&frames[1].1), None, 400, &mut rng, &mut patches).unwrap();
        g.bench_function(BenchmarkId::new("random_400", n), |b| {
            b.iter(|| classifier.histogram_of_patches(black_box(&patches)))
        });
    }
    g.finish();

    let mut g = c.benchmark_group("indoor_knn");
    for count in [500usize, 1000, 50_000] {
        let m = model(dict.clone(), count);
        let knn = Knn::new(&m.histograms).unwrap();
        let points: Vec<[f32; 20]> = m.histograms.iter().map(|h| h.as_slice().try_into().unwrap()).collect();
        let tree: kiddo::ImmutableKdTree<f32, 20> = kiddo::ImmutableKdTree::new_from_slice(&points).unwrap();
        let queries: Vec<Vec<f32>> =
            m.histograms.iter().take(64).map(|h| h.iter().map(|v| v * 0.9 + 0.005).collect()).collect();
        let (mut scratch, mut out) = (Vec::new(), Vec::new());
        let mut qi = 0;
        g.bench_function(BenchmarkId::new("brute_force_k5", count), |b| {
            b.iter(|| {
                qi = (qi + 1) % queries.len();
                knn.nearest(black_box(&queries[qi]), 5, None, &mut scratch, &mut out);
                out.len()
            })
        });
        let five = NonZero::new(5usize).unwrap();
        g.bench_function(BenchmarkId::new("kiddo_kd_tree_k5", count), |b| {
            b.iter(|| {
                qi = (qi + 1) % queries.len();
                let q: [f32; 20] = queries[qi].as_slice().try_into().unwrap();
                tree.query(black_box(&q)).nearest_n::<kiddo::SquaredEuclidean<f32>>(five).execute().len()
            })
        });
    }
    g.finish();

    let mut g = c.benchmark_group("indoor_resampling");
    let mut rng = rand::rngs::StdRng::seed_from_u64(4);
    let weights: Vec<f64> = (0..100).map(|_| rng.random::<f64>()).collect();
    g.bench_function("systematic_100", |b| b.iter(|| systematic(black_box(&weights), 0.37)));
    g.bench_function("resampling_wheel_100", |b| b.iter(|| resampling_wheel(black_box(&weights), &mut rng)));
    g.finish();

    // The particle filter's point estimate: the seed's O(M^2) MAP against the O(M) mode,
    // on the same 500 particles after a few updates.
    let mut g = c.benchmark_group("indoor_estimate");
    let mut pf = ParticleFilter::new(500, Vector2::new(-4.0, -4.0), Vector2::new(4.0, 4.0), 1);
    let process = Gaussian2::new(&(Matrix2::identity() * 0.0025)).unwrap();
    let rank = [Gaussian2::new(&(Matrix2::identity() * 0.04)).unwrap()];
    for i in 0..20 {
        pf.predict(Vector2::new(0.02, 0.0), &process);
        pf.update(&[Vector2::new(0.02 * i as f64, 0.5)], &rank);
    }
    g.bench_function("map_500", |b| b.iter(|| black_box(&pf).map_estimate(&process)));
    g.bench_function("mode_500", |b| b.iter(|| black_box(&pf).mode_estimate(0.2)));
    g.finish();

    let mut g = c.benchmark_group("indoor_frame");
    let m = model(dict.clone(), 1000);
    // The seed's 100 particles against the default 500, in the same run.
    for (name, motion, particles) in [
        ("velocity_100", MotionModel::Velocity, 100),
        ("velocity_500", MotionModel::Velocity, 500),
        ("noise_100", MotionModel::Noise, 100),
    ] {
        let params =
            LocalizerParams { k: 5, particles, samples: 400, motion, velocity_sigma_m_s: 0.1, seed: 1 };
        let mut loc = Localizer::new(&m, params).unwrap();
        let mut t = 0.0;
        let v = nalgebra::Vector2::new(0.3, -0.1);
        g.bench_function(BenchmarkId::new("loop_400_samples_knn_1000", name), |b| {
            b.iter(|| {
                t += 1.0 / 15.0;
                loc.step_frame(t, &pre, black_box(&frames[2].0), Some(&frames[2].1), None, Some(v))
                    .unwrap()
                    .position
            })
        });
    }
    g.finish();
}

criterion_group!(benches, stages);
criterion_main!(benches);
