"""Segmentation under a receive-coil bias field, with and without N4 correction.

Two SYNTHETIC legs, each segmented with the settings of its shipped config: the demo leg (96 × 96 × 5 voxels
of 0.156 × 0.156 × 0.5 cm, ``configs/demo.yaml``) and Example 2's leg at the paper's pixel (176 × 176 × 25 of
0.078 × 0.078 × 0.5 cm, ``configs/lower_leg.yaml``), both seed 0 as shipped, are rendered with a smooth multiplicative intensity field ``1 + b · f(x)`` (``f`` a unit-variance random field with
correlation lengths 8 × 8 × 20 cm, :func:`pixmuscle.synth.noise.smooth_field`) of amplitude ``b`` = 0.03 (the
shipped phantoms' own), 0.35 and 0.70, and segmented with the demo's settings, ``segment.bias_correction``
none and n4. Each segmentation is scored against the phantom's truth (Dice: outline, bone, fat, connective
tissue, mean and lowest muscle). The random stream is the same for every amplitude (same noise, same field
shape), so the rows differ only by the field's strength and the correction.

Run: ``python benchmarks/bench_bias_field.py``; writes ``benchmarks/results/bench_bias_field.{json,md}``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
AMPLITUDES = (0.03, 0.35, 0.70)
#: phantom → (make_leg_phantom arguments, config whose segment settings and seeds are used)
PHANTOMS = {"demo": (dict(shape=(96, 96, 5), pixel_cm=0.156, slice_cm=0.5, seed=0), "demo.yaml"),
            "paper": (dict(shape=(176, 176, 25), pixel_cm=0.078125, slice_cm=0.5, seed=0), "lower_leg.yaml")}


def run_case(phantom: str, amplitude: float, correction: str, work: Path) -> dict:
    from pixmuscle.pipeline import load_config
    from pixmuscle.segmentation.scoring import score_segmentation
    from pixmuscle.stages.segment import run_segment
    from pixmuscle.synth.leg import make_leg_phantom
    from pixmuscle.synth.write import write_phantom

    kwargs, config = PHANTOMS[phantom]
    prefix = f"leg_{phantom}_bias{amplitude:.2f}"
    if not (work / f"{prefix}_mri.nii.gz").exists():
        write_phantom(make_leg_phantom(**kwargs, bias=amplitude),
                      work, prefix)
    seg = load_config(ROOT / "configs" / config).segment
    seg = dataclasses.replace(seg, mri=work / f"{prefix}_mri.nii.gz", dti_tensor=work / f"{prefix}_dti_tensor.nii.gz",
                              imct_mask=work / f"{prefix}_imct.nii.gz", imat_mask=work / f"{prefix}_imat.nii.gz",
                              aponeurosis_mask=work / f"{prefix}_aponeurosis.nii.gz" if seg.aponeurosis_mask else None,
                              bias_correction=correction, qc_png=False)
    t = time.perf_counter()
    res = run_segment(seg, work / f"{prefix}_{correction}" / "segmentation.h5")
    wall = time.perf_counter() - t
    from pixmuscle.imaging.nifti import load_volume

    truth = json.loads((work / f"{prefix}_truth.json").read_text())
    score = score_segmentation(res.labels, res.muscle_id, load_volume(work / f"{prefix}_labels.nii.gz", kind="labels").data,
                               load_volume(work / f"{prefix}_muscle_id.nii.gz", kind="labels").data, truth["muscle_names"])
    return {"phantom": phantom, "shape": list(kwargs["shape"]), "bias_amplitude": amplitude, "bias_correction": correction, "segment_s": round(wall, 1),
            "dice": {"outline": round(score["outline"], 4),
                     **{k: round(v, 4) for k, v in score["tissues"].items() if k != "background"},
                     "muscle_mean": round(score["muscle_mean"], 4), "muscle_min": round(score["muscle_min"], 4)}}


def main() -> int:
    run = Run(defaults=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for phantom in PHANTOMS:
            for a in AMPLITUDES:
                for corr in ("none", "n4"):
                    rows.append(run_case(phantom, a, corr, Path(tmp)))
                print(json.dumps(rows[-1]), flush=True)
    rec = {**run.fields(),
           "phantoms": {k: f"SYNTHETIC make_leg_phantom({v[0]}, bias=b), segmented as configs/{v[1]}" for k, v in PHANTOMS.items()},
           "cases": rows}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "bench_bias_field.json").write_text(json.dumps(rec, indent=2) + "\n")
    lines = ["# Segmentation under a bias field (SYNTHETIC legs)", "",
             f"`{rec['command']}` at {rec['commit']}, {rec['utc']}, load average {rec['load_average']['before']} → "
             f"{rec['load_average']['after']}.", "",
             "| phantom | bias amplitude | correction | outline | bone | fat | connective tissue | muscle mean | muscle min | segment (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = r["dice"]
        lines.append(f"| {r['phantom']} | ±{r['bias_amplitude'] * 100:.0f} % | {r['bias_correction']} | {d['outline']:.3f} | {d['bone']:.3f} | "
                     f"{d['fat']:.3f} | {d['connective_tissue']:.3f} | {d['muscle_mean']:.3f} | {d['muscle_min']:.3f} | "
                     f"{r['segment_s']} |")
    (OUT / "bench_bias_field.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
