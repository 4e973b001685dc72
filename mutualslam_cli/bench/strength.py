"""How the default regulariser coefficients are chosen: the same measured strength for EWC, MAS and SI.

The three importances differ by orders of magnitude for the same coefficient, so the coefficients
are set by what the regulariser *does*, never by the accuracy it buys: its mean *shrink*
(``adaptation.reg.shrink.mean``, :mod:`~mutualslam_cli.adapt.regularizers`), the share of each
batch's Adam displacement the proximal step takes back. Procedure:

1. The paper's EWC (β = 5e7, max_F = 1e-3, scheme ``replay+ewc``) sets the target shrink.
2. For MAS (λ) and SI (λ), starting from the current value, run the same sequence and rescale the
   coefficient by ``target / shrink`` (the shrink is close to proportional to the coefficient while
   it is small) until it is within ``tol`` of the target, at most ``max_runs`` runs each.

The sequence is a rendered synthetic room in the target domain (not one of the evaluation
windows; no GT is read, only the optimiser's behaviour). GT depth and poses are not used; the front
end is our VO. Run it with (:func:`run_strength`)::

    mslam bench strength --out results/strength [--frames 200] [--seed 3]

It prints one line per run and writes ``strength.json`` with the chosen coefficients.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TypedDict

from mutualslam_cli.config import RunConfig, load_config
from mutualslam_cli.datasets import synthetic

#: scheme → the coefficient key calibrated for it
CALIBRATED = {"replay+mas": "adapt.mas_lambda", "replay+si": "adapt.si_lambda"}
#: settings of every calibration run: the adaptation is what is measured; BA and dense evaluation are not
RUN_SETTINGS = ["ba.enabled=false", "eval.stride=1000", "eval.online=false", "threads=1"]


class Trial(TypedDict):
    """One calibration run: the coefficient tried and the mean shrink it gave."""

    value: float
    shrink: float


class Calibrated(Trial):
    """A scheme's calibration: the config key, the chosen :class:`Trial` and every trial in order."""

    key: str
    runs: list[Trial]


Calibration = dict[str, "float | Calibrated"]
""":func:`calibrate`'s result: ``"target"`` → the EWC shrink, each calibrated scheme → :class:`Calibrated`."""


def shrink_of(seq: Path, out: Path, scheme: str, sets: list[str]) -> float:
    """Mean shrink of ``scheme`` on ``seq`` with the overrides ``sets`` (one ``mslam run``)."""
    from mutualslam_cli.pipeline import run_sequence

    cfg: RunConfig = load_config(None, [*RUN_SETTINGS, f"adapt.scheme={scheme}", *sets])
    res = run_sequence(seq, cfg, out)
    value = res.summary.number("adaptation.reg.shrink.mean")
    if value is None:
        raise RuntimeError(f"{res.folder}: no adaptation.reg.shrink.mean")
    return float(value)


def calibrate(seq: Path, out: Path, tol: float = 0.1, max_runs: int = 5) -> Calibration:
    """Steps 1–2 of the module docstring; returns ``{"target": shrink, scheme: {key, value, shrink, runs}}``."""
    target = shrink_of(seq, out / "ewc", "replay+ewc", [])
    print(f"replay+ewc (paper β, max_F): shrink {target:.4g}", flush=True)
    result: Calibration = {"target": target}
    base = load_config(None, [])
    for scheme, key in CALIBRATED.items():
        section, name = key.split(".")
        value = float(getattr(getattr(base, section), name))
        runs: list[Trial] = []
        for _ in range(max_runs):
            s = shrink_of(seq, out / f"{scheme}-{value:.6g}", scheme, [f"{key}={value:.6g}"])
            runs.append({"value": value, "shrink": s})
            print(f"{scheme} {key}={value:.4g}: shrink {s:.4g}", flush=True)
            if abs(s - target) <= tol * target or s <= 0:
                break
            value = float(f"{value * target / s:.2g}")  # two significant digits: a value a person can read
        best = min(runs, key=lambda r: abs(r["shrink"] - target))
        result[scheme] = {"key": key, "value": best["value"], "shrink": best["shrink"], "runs": runs}
    return result


def run_strength(out: Path = Path("results/strength"), sequence: Path | None = None, frames: int = 200,
                 seed: int = 3) -> Calibration:
    """The whole procedure: renders the room (``frames`` frames, 640×480, rendering seed ``seed``) into
    ``out/room<frames>-seed<seed>`` unless ``sequence`` is given or it is there already, :func:`calibrate`s on it
    under ``out``, writes ``out/strength.json`` and prints the chosen coefficients; returns :func:`calibrate`'s
    result."""
    out = Path(out)
    seq = sequence
    if seq is None:
        seq = out / f"room{frames}-seed{seed}"
        if not (seq / "rgb.txt").is_file():
            synthetic.write_tum(synthetic.iter_render("room", frames, 640, 480, seed, "target"), seq)
    result = calibrate(seq, out)
    (out / "strength.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: (v if not isinstance(v, dict) else {"key": v["key"], "value": v["value"],
                                                               "shrink": v["shrink"]})
                      for k, v in result.items()}, indent=2))
    return result
