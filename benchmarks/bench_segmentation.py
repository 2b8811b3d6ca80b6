"""Level-set segmentation speed.

1. Two-phase Chan–Vese on ``skimage.data.camera()`` (512 x 512, scaled to [0, 1]): ours vs
   ``skimage.segmentation.chan_vese`` with the same mu, lambdas, dt, tol, iteration limit and
   initial level set (target: >= 3x faster); also the pixel agreement.
2. Multiphase Vese–Chan, K = 3 level sets, 4 channels (MRI + e1, e2, e3, the paper's setting:
   lambda = 0.02, mu = 1 on the [0, 255] scale), on a 256 x 256 slice of the SYNTHETIC leg
   phantom (target: <= 2 s per slice): seed initialisation as in the pipeline, and a fixed
   300 sweeps from checkerboards (worst case: the iteration limit).
3. The whole ``segment_volume`` (outer boundary, bones, muscles, labels) per 256 x 256 slice.

Run: ``python benchmarks/bench_segmentation.py``; writes
``benchmarks/results/bench_segmentation.{json,md}``. Timings are wall-clock, best of
``repeats``, after a warm-up call (numba compilation reported separately).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"


def best_of(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def bench_camera(repeats=3, max_iter=200):
    from skimage import data
    from skimage.segmentation import chan_vese as sk_chan_vese

    from pixmuscle.segmentation.chan_vese import chan_vese

    img = data.camera().astype(float)
    img = (img - img.min()) / (img.max() - img.min())
    kw = dict(mu=0.25, lambda1=1.0, lambda2=1.0, dt=0.5, tol=1e-3)
    t = time.perf_counter()
    chan_vese(img[:16, :16], max_iter=2, **kw)
    compile_s = time.perf_counter() - t
    ours_s, ours = best_of(lambda: chan_vese(img, max_iter=max_iter, init="checkerboard", **kw),
                           repeats)
    sk_s, ref = best_of(lambda: sk_chan_vese(img, max_num_iter=max_iter,
                                             init_level_set="checkerboard",
                                             extended_output=True, **kw), max(1, repeats - 1))
    n_sk = len(ref[2])
    return {
        "image": "skimage.data.camera() 512x512 scaled to [0, 1]",
        "params": dict(kw, max_iter=max_iter, init="checkerboard"),
        "ours_s": ours_s, "skimage_s": sk_s, "speedup": sk_s / ours_s,
        "ours_iterations": ours.n_iter, "skimage_iterations": n_sk,
        "ours_ms_per_iteration": 1e3 * ours_s / ours.n_iter,
        "skimage_ms_per_iteration": 1e3 * sk_s / n_sk,
        "agreement": float(np.mean(ours.segmentation == ref[0])),
        "numba_compile_s": compile_s,
    }


def leg_slice():
    from pixmuscle.imaging.dti import resample_tensor_to_grid, tensor_from_components
    from pixmuscle.synth.leg import make_leg_phantom

    ph = make_leg_phantom(shape=(256, 256, 2), pixel_cm=0.078125, seed=0)
    d, covered = resample_tensor_to_grid(tensor_from_components(ph.dti_tensor, "fsl"),
                                         ph.dti_affine, ph.mri.shape, ph.affine)
    return ph, d, covered


def seeds_of(ph, k):
    seeds = {}
    for m, name in enumerate(ph.muscle_names, 1):
        depth = ndi.distance_transform_edt(ph.muscle_id[:, :, k] == m)
        i, j = np.unravel_index(np.argmax(depth), depth.shape)
        seeds[name] = [[float(i), float(j), float(k)]]
    return seeds


def bench_multiphase(ph, d, covered, repeats=3):
    from pixmuscle.segmentation.assemble import fiber_data
    from pixmuscle.segmentation.features import fiber_channels, normalize_intensity
    from pixmuscle.segmentation.multiphase import (
        multiphase_chan_vese,
        seed_features,
        seed_regions,
    )

    k = 0
    valid, v, _ = fiber_data(d, covered)
    u = normalize_intensity(ph.mri)[:, :, k]
    ch = np.concatenate([u[None], fiber_channels(v[:, :, k], valid[:, :, k], "canonical")])
    mask = valid[:, :, k] & (ph.labels[:, :, k] != 4)
    seeds = [np.array([[int(p[0]), int(p[1])]]) for p in
             (s[0] for s in seeds_of(ph, k).values())]
    kw = dict(n_levelsets=3, mu=1.0, lambdas=0.02, mask=mask, stop="regions", tol=5e-4,
              window=10, energy_scale="variance", reinit_every=5)

    def seeded():
        feats = seed_features(ch, seeds, mask=mask)
        init = seed_regions(ch, feats, 8, mask=mask, lambdas=np.full(4, 0.02))
        return multiphase_chan_vese(ch, init=init, max_iter=300, **kw)

    def fixed():
        # stop="phi" with tol=0 never stops early: exactly 300 sweeps
        return multiphase_chan_vese(ch, init="checkerboard", max_iter=300,
                                    **dict(kw, tol=0.0, stop="phi"))

    seeded()
    s_seed, r_seed = best_of(seeded, repeats)
    s_fixed, r_fixed = best_of(fixed, repeats)
    return {
        "slice": "SYNTHETIC leg phantom, 256x256, 0.078125 cm pixels",
        "channels": "MRI + canonical e1, e2, e3 (4)", "n_levelsets": 3,
        "voxels_in_mask": int(mask.sum()),
        "seed_init_s": s_seed, "seed_init_iterations": r_seed.n_iter,
        "fixed_300_sweeps_s": s_fixed, "fixed_iterations": r_fixed.n_iter,
        "ms_per_sweep": 1e3 * s_fixed / r_fixed.n_iter,
    }


def bench_pipeline(ph, d, covered, repeats=2):
    from pixmuscle.segmentation.config import SegmentConfig
    from pixmuscle.segmentation.volume import segment_volume

    cfg = SegmentConfig(seeds=seeds_of(ph, 1), seed_units="voxel")

    def go():
        return segment_volume(ph.mri, ph.affine, d, covered, ph.imct_mask, ph.imat_mask, cfg)

    go()
    s, res = best_of(go, repeats)
    n = ph.mri.shape[2]
    dice = [2 * np.sum((res.muscle_id == m) & (ph.muscle_id == m))
            / (np.sum(res.muscle_id == m) + np.sum(ph.muscle_id == m))
            for m in range(1, len(ph.muscle_names) + 1)]
    return {"volume": list(ph.mri.shape), "total_s": s, "s_per_slice": s / n,
            "mean_muscle_dice": float(np.mean(dice))}


def main():
    t0 = time.perf_counter()
    record = Run(defaults=True)
    load0 = record.load_before[0]
    cam = bench_camera()
    ph, d, covered = leg_slice()
    mp = bench_multiphase(ph, d, covered)
    pipe = bench_pipeline(ph, d, covered)
    result = {
        "chan_vese_camera": cam,
        "multiphase_256": mp,
        "segment_volume_256": pipe,
        "targets": {"camera_speedup_min": 3.0, "multiphase_s_per_slice_max": 2.0},
        "met": {"camera_speedup": cam["speedup"] >= 3.0,
                "multiphase_seeded": mp["seed_init_s"] <= 2.0,
                "multiphase_300_sweeps": mp["fixed_300_sweeps_s"] <= 2.0},
        "wall_s": time.perf_counter() - t0,
        **record.fields(),
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "bench_segmentation.json").write_text(json.dumps(result, indent=2) + "\n")
    md = [
        "## Segmentation (level sets)",
        "",
        "| case | ours | reference / target | note |",
        "|---|---|---|---|",
        f"| Chan–Vese, camera 512², {cam['ours_iterations']} it | {cam['ours_s']:.2f} s "
        f"({cam['ours_ms_per_iteration']:.1f} ms/it) | skimage {cam['skimage_s']:.2f} s "
        f"({cam['skimage_ms_per_iteration']:.1f} ms/it) | **{cam['speedup']:.1f}x** faster "
        f"(target ≥ 3x), pixel agreement {100 * cam['agreement']:.2f} % |",
        f"| multiphase K=3, 4 ch, 256², seed init | {mp['seed_init_s']:.2f} s "
        f"({mp['seed_init_iterations']} it) | ≤ 2 s/slice | |",
        f"| multiphase K=3, 4 ch, 256², 300 sweeps | {mp['fixed_300_sweeps_s']:.2f} s "
        f"({mp['ms_per_sweep']:.1f} ms/sweep) | ≤ 2 s/slice | iteration limit reached |",
        f"| segment_volume 256²×{ph.mri.shape[2]} | {pipe['s_per_slice']:.2f} s/slice | | "
        f"all steps; mean muscle Dice {pipe['mean_muscle_dice']:.3f} |",
        "",
        f"numba compilation (first call, cached afterwards): {cam['numba_compile_s']:.1f} s; "
        f"{result['machine']['cpus']} CPUs, 1-min load average {load0:.1f} at the start "
        "(the machine is shared; timings scale with it), best of 2-3 runs.",
    ]
    (OUT / "bench_segmentation.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return result


if __name__ == "__main__":
    main()
