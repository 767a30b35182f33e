#!/usr/bin/env python3
"""`make bench`: one table of the hot stages (criterion medians of `cargo bench`, read from
target/criterion) beside the frames/s and accuracy of full pipeline runs made in the same
invocation on rendered data (cached in BENCH_DATA, rendered once).

    tools/bench_table.py [--data target/bench-data] [--bin target/release/mavloc]

The `indoor whole frame` row is the per-frame work of a flight frame as `mavloc indoor run`
does it, decoding excluded and preparation included: 400 patches gathered, derotated and
normalised from a 640x480 frame, their histogram, k-NN over 1000 views, 500 particles.
"""
import argparse, json, os, subprocess, sys

ROWS = [
    # (label, criterion path under target/criterion)
    ("indoor whole frame", "indoor_frame/loop_400_samples_knn_1000/velocity_500"),
    ("indoor whole frame, 100 particles", "indoor_frame/loop_400_samples_knn_1000/velocity_100"),
    ("indoor: gather 400 patches (derotate, normalise)", "indoor_prepare/sample 400 patches 640x480 (flight)"),
    ("indoor: whole canvas (training only)", "indoor_prepare/whole canvas 640x480 (training)"),
    ("indoor: histogram of 400 patches, 20 textons", "indoor_histogram/random_400/20"),
    ("indoor: k-NN over 1000 views (brute force)", "indoor_knn/brute_force_k5/1000"),
    ("indoor: particle estimate, O(M) mode, 500", "indoor_estimate/mode_500"),
    ("indoor: particle estimate, seed's O(M^2) MAP, 500", "indoor_estimate/map_500"),
    ("area: read a 960x540 frame (png crate)", "area_read_frame_png_960x540"),
    ("area: read a 960x540 frame (OpenCV imdecode, before)", "area_read_frame_png_960x540_opencv"),
    ("area: band (distance transform)", "area_band_distance_transform"),
    ("area: SIFT in the band, pieces", "area_sift_in_band_2000"),
    ("area: SIFT in the band, one box (before)", "area_sift_in_band_one_box"),
    ("area: UKF updates, 200 landmarks", "area_ukf_update_200_landmarks/local_yaw_pitch"),
    ("area: whole frame, steady state", "area_whole_frame_steady_state"),
    ("area: bundle adjustment, 18 photos, 4000 tie points", "area_refine_18_photos_4000_tracks"),
]

def median_us(path):
    f = os.path.join("target/criterion", path, "new/estimates.json")
    if not os.path.exists(f):
        return None
    return json.load(open(f))["median"]["point_estimate"] / 1000.0

def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"bench: failed: {' '.join(cmd)}\n{r.stderr[-2000:]}")
    return r.stdout

def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="target/bench-data")
    ap.add_argument("--bin", default="target/release/mavloc")
    a = ap.parse_args()
    d = a.data
    os.makedirs(d, exist_ok=True)
    # Indoor: 1000 views, 1000 flight frames with a reality gap (scenario seed 3).
    if not os.path.exists(f"{d}/floor-train/telemetry.jsonl"):
        run([a.bin, "sim", "render", "--scenario", "indoor-floor", "--views", "1000", "--out", f"{d}/floor-train", "--force"])
    if not os.path.exists(f"{d}/floor-flight/telemetry.jsonl"):
        run([a.bin, "sim", "render", "--scenario", "indoor-floor", "--frames", "1000", "--brightness", "15",
             "--contrast", "0.9", "--blur-px", "3", "--out", f"{d}/floor-flight", "--force"])
    if not os.path.exists(f"{d}/floor.model"):
        run([a.bin, "indoor", "train", "--dataset", f"{d}/floor-train", "--out", f"{d}/floor.model"])
    run([a.bin, "indoor", "run", "--dataset", f"{d}/floor-flight", "--model", f"{d}/floor.model", "--out", f"{d}/indoor-run"])
    ie = json.loads(run([a.bin, "eval", "indoor", "--dataset", f"{d}/floor-flight", "--result", f"{d}/indoor-run", "--json"]))
    isum = json.load(open(f"{d}/indoor-run/summary.json"))
    # Area: full laps of the coastline and cliff missions at 960x540, as the README's
    # "Measured" table runs them (downscale 1, the band at the seed's 50 px of full HD).
    area = {}
    for sc in ("coastline", "cliff"):
        data = f"{d}/{sc}-960"
        if not os.path.exists(f"{data}/telemetry.jsonl"):
            run([a.bin, "sim", "render", "--scenario", sc, "--width", "960", "--height", "540", "--out", data, "--force"])
        run([a.bin, "area", "--dataset", data, "--out", f"{d}/area-{sc}", "--set", "area.downscale=1", "--set", "area.band_px=25"])
        ev = json.loads(run([a.bin, "eval", "area", "--dataset", data, "--result", f"{d}/area-{sc}", "--json"]))
        area[sc] = (ev, json.load(open(f"{d}/area-{sc}/summary.json")))

    print("| stage | median |")
    print("|---|---|")
    for label, path in ROWS:
        m = median_us(path)
        if m is not None:
            print(f"| {label} | {m:,.1f} us |")
    frame_ms = isum["prepare_ms"] + isum["localize_ms"]
    print(f"| indoor run, 1000 frames: whole frame without decoding (prepare {isum['prepare_ms']:.3f} + localise "
          f"{isum['localize_ms']:.3f} ms) | {frame_ms * 1000:,.1f} us ({1000 / frame_ms:,.0f} frames/s; with "
          f"decoding {isum['frames_per_s']:,.0f} frames/s) |")
    print(f"| indoor accuracy, same run (1000 views) | RMS {ie['rmse_m']:.3f} m, max {ie['max_err_m']:.3f} m "
          f"({ie['max_err_after_2s_m']:.3f} m after the first 2 s) |")
    for sc, (ev, su) in area.items():
        print(f"| area run, {sc} full lap 960x540, {su['frames']} frames: read+segment {su.get('prepare_ms', 0):.1f}, band "
              f"{su['band_ms']:.1f}, SIFT {su['sift_ms']:.1f}, match+estimate {su['match_estimate_ms']:.1f} ms | "
              f"{su['frames_per_s']:,.1f} frames/s |")
        print(f"| area accuracy, same run | {ev['landmarks']} landmarks, mean {ev['mean_m']:.2f} m, max {ev['max_m']:.2f} m, "
              f"{ev['gt20']} over 20 m |")

if __name__ == "__main__":
    main()
