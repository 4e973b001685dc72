"""The schema of ``summary.json``: every key a run, ``mslam eval-depth`` or ``mslam fuse`` may write, with its
kind, unit and meaning — declared once, here.

:class:`~mutualslam_cli.results.summary.Summary` refuses a key or a value this schema does not hold (a stage that
renames a key fails its tests, not a report later), :class:`~mutualslam_cli.results.record.RunSummary` reads a
written file back through it, and :func:`json_schema` describes it for other tools (``summary.schema.json``, shipped
with the package: ``python -m mutualslam_cli.results.schema`` writes it).

A field's ``pattern`` is a dotted key whose ``{name}`` parts take the values :data:`CHOICES` lists for that name
(``depth.pcd.{scaling}.{model}`` is six keys); a name without choices (``timing.stage_s.{stage}``) takes any
``[a-z0-9_]+``. Every value may also be ``null``, its reason under ``notes`` with the same key.

Version history: 1 — ``summary.json`` without ``schema_version`` (every run before typed records); 2 — this
schema, ``schema_version: 2`` at the top level; the keys are version 1's.
"""

from __future__ import annotations

import itertools
import json
import re
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Literal

from mutualslam_cli.errors import SchemaError
from mutualslam_cli.types import JSON, JSONObject

#: The version :class:`~mutualslam_cli.results.summary.Summary` writes.
SCHEMA_VERSION = 2
#: The versions :class:`~mutualslam_cli.results.record.RunSummary` reads (1: files without ``schema_version``).
READABLE = (1, 2)
#: The shipped JSON Schema (:func:`json_schema`).
SCHEMA_FILE = Path(__file__).with_name("summary.schema.json")

Kind = Literal["number", "integer", "flag", "text", "list", "object"]

#: The values a ``{name}`` of a pattern takes.
CHOICES: dict[str, tuple[str, ...]] = {
    "model": ("pretrained", "adapted"),
    "dense_model": ("pretrained", "adapted", "gt"),
    "scaling": ("lsq", "median", "seq_lsq"),
    "kf": ("", "_nonkf"),
    "quarter": ("q1", "q2", "q3", "q4"),
    "quarter_model": ("pretrained", "adapted", "online"),
    "traj": ("vo", "ba", "bridged", "posenet", "all_frames", "all_frames_ba", "all_frames_bridged"),
    "local": ("vo", "ba"),
    "credit": ("credit", "credit_kf"),
    "credit_col": ("vo", "ba", "bridged", "live", "frames"),
    "lost": ("too_few_tracks", "failed_alignment", "failed_init"),
    "rescue": ("seeds", "wide"),
    "l_val": ("validations", "min", "median", "longest_below_tau", "map_median_depth"),
    "dense_prefix": ("", "frame_scale.", "gt_scale."),
    "dense_score": ("accuracy_m", "completeness_m", "fscore_5cm", "precision_5cm", "recall_5cm",
                    "accuracy_median_m", "completeness_median_m"),
    "dense_stat": ("metric_scale_median", "metric_scale_log_std", "fallback_frames"),
    "mesh": ("blocks", "triangles", "frames_capped"),
    "ba_count": ("keyframes", "n_blocks", "n_culled", "n_diverged", "n_dropped", "n_judged_elsewhere",
                 "n_nearby_targets", "n_outlier_blocks", "n_refined", "n_targets", "n_unrefined", "iterations"),
    "finetune_ms": ("finetune_ms", "finetune_kf_ms", "finetune_batch_ms", "finetune_consolidate_ms"),
    "finetune_s": ("finetune_steps_s", "finetune_consolidate_s"),
    "bwt": ("vs_pretrained", "vs_online"),
    "step_stat": ("median", "p90", "p99", "max"),
    "verdict": ("right", "wrong"),
    "live": ("points_reused", "points_fused", "old_share", "map_units"),
    "check": ("checks", "drift_max", "drift_min"),
    "map_stage": ("vo", "culled", "ba"),
    "outliers": ("injected", "culled", "dropped"),
    "agg": ("mean", "median"),
    "scale_stat": ("max", "min", "max_over_min"),
    "loop_count": ("candidates", "accepted", "rejected", "closed_right"),
    "recall": ("revisits", "found", "verified", "closed", "refused"),
    "ba_cost": ("cost0", "cost"),
    "per_frame_scaling": ("frame_scale", "gt_scale"),
    "dense_scale": ("scale", "metric_scale"),
    "dense_count": ("block_cap", "segments", "frames", "frames_reference"),
    "dense_figure": ("memory_cap_mb", "sim3_scale", "time_s"),
}


@dataclass(frozen=True)
class Field:
    """One key (or family of keys) of ``summary.json``.

    Attributes:
        pattern: the dotted key, ``{name}`` parts as in the module docstring.
        kind: ``number`` (int or float), ``integer``, ``flag`` (bool), ``text``, ``list`` or ``object``.
        unit: the unit of a number (``%``, ``m``, ``s``, ``ms``, ``count``…), ``""`` where none.
        doc: what it means, in one line.
    """

    pattern: str
    kind: Kind
    unit: str
    doc: str

    @property
    def names(self) -> tuple[str, ...]:
        """The ``{name}`` parts of the pattern, in order."""
        return tuple(re.findall(r"\{(\w+)\}", self.pattern))

    def keys(self) -> tuple[str, ...]:
        """Every concrete key of a pattern whose names all have choices; ``()`` for an open family."""
        names = self.names
        if any(n not in CHOICES for n in names):
            return ()
        return tuple(self.pattern.format(**dict(zip(names, vals)))
                     for vals in itertools.product(*(CHOICES[n] for n in names)))

    def regex(self) -> str:
        """The pattern as a regular expression (choices as alternatives, open names as ``[a-z0-9_]+``)."""
        out = re.escape(self.pattern)
        for n in self.names:
            alt = "|".join(re.escape(c) for c in CHOICES[n]) if n in CHOICES else r"[a-z0-9_]+"
            out = out.replace(re.escape("{" + n + "}"), f"(?:{alt})", 1)
        return out


def _f(pattern: str, kind: Kind, unit: str, doc: str) -> Field:
    return Field(pattern, kind, unit, doc)


N: Kind = "number"
INT: Kind = "integer"
B: Kind = "flag"
T: Kind = "text"

#: Every field of ``summary.json`` (module docstring).
FIELDS: tuple[Field, ...] = (
    # --- identity
    _f("sequence.name", T, "", "the sequence's name (datasets.yaml or the folder's)"),
    _f("sequence.frames", INT, "count", "frames of the sequence"),
    _f("scheme", T, "", "adaptation scheme (or an external model's name)"),
    _f("seed", INT, "", "random seed"),
    _f("run.{device}", T, "", "the device the network ran on: device, device_name, device_label, cuda_version…"),
    _f("run.device_memory_gb", N, "GiB", "the device's memory"),
    # --- depth (Eq. 11: PCD, δ < 0.1; e_si)
    _f("depth.pcd{kf}.{scaling}.{model}", N, "%", "mean percent-correct depth per frame under a scaling"),
    _f("depth.pcd_pooled{kf}.{scaling}.{model}", N, "%", "percent-correct depth over the pooled pixels"),
    _f("depth.pcd.none.{model}", N, "%", "percent-correct depth without any scaling (metric models)"),
    _f("depth.esi{kf}.{model}", N, "", "mean scale-invariant error per frame"),
    _f("depth.pcd_online{kf}.{scaling}", N, "%", "PCD of each frame by the model of that frame's time"),
    _f("depth.esi_online", N, "", "scale-invariant error by the model of each frame's time"),
    _f("depth.quarter_pcd_lsq.{quarter_model}.{quarter}", N, "%", "per-frame lsq PCD on a quarter of the frames"),
    _f("depth.bwt.{bwt}", N, "%", "backward transfer on the first quarter: final minus a reference's PCD"),
    _f("depth.frames_evaluated", INT, "count", "frames whose depth was scored"),
    _f("depth.eval_stride", INT, "frames", "every k-th frame with GT depth is scored"),
    _f("depth.fast_path", B, "", "the network ran its fast (bf16/channels-last/OpenVINO) path"),
    _f("depth.exported_frames", INT, "count", "frames whose depth maps were saved"),
    # --- trajectory (ATE: one Sim(3) over the trajectory)
    _f("trajectory.ate_rmse_m.{traj}", N, "m", "ATE RMSE after one Sim(3) alignment"),
    _f("trajectory.ate_rmse_m_per_segment.{traj}", N, "m", "ATE RMSE, one Sim(3) per segment"),
    _f("trajectory.{credit}.{credit_col}", N, "m", "ATE over the frames every column tracked (like for like)"),
    _f("trajectory.local_scale.{local}.{scale_stat}", N, "", "local Sim(3) scale over windows: max, min, max_over_min"),
    _f("trajectory.local_ate_m.{local}", N, "m", "ATE RMSE with one Sim(3) per window"),
    # --- front end
    _f("vo.keyframes", INT, "count", "keyframes made"),
    _f("vo.tracked_fraction", N, "", "share of frames tracked"),
    _f("vo.segments", INT, "count", "segments (restarts after a loss)"),
    _f("vo.mode", T, "", "front end: svo (ours) or an oracle"),
    _f("vo.from_cache", B, "", "the whole front end came from the cache"),
    _f("vo.frames_from_cache", INT, "count", "frames replayed from the cache"),
    _f("vo.relocalisations", INT, "count", "relocalisations accepted"),
    _f("vo.relocalisations_rejected", INT, "count", "relocalisation candidates refused"),
    _f("vo.relocalisations_{verdict}", INT, "count", "accepted relocalisations right / wrong against GT"),
    _f("vo.losses", INT, "count", "times the front end lost track"),
    _f("vo.frames_lost.{lost}", INT, "count", "untracked frames by the reason of their loss"),
    _f("vo.rescued.{rescue}", INT, "count", "weak frames whose pose a rescue kept"),
    _f("vo.points_reused", INT, "count", "map points re-observed after leaving the view"),
    _f("vo.points_fused", INT, "count", "map points fused with a duplicate"),
    _f("vo.old_share", N, "%", "share of tracked map points older than the window"),
    _f("vo.live.{live}", N, "", "the live map's points reused/fused, old share (%) and map units"),
    _f("vo.bridges", INT, "count", "bridges made between segments"),
    _f("vo.bridges_credit", INT, "count", "bridges planned on the front end's own map"),
    _f("vo.bridges_refused", INT, "count", "bridges refused"),
    _f("vo.merges", INT, "count", "segments merged into an older map"),
    _f("vo.merge_queries", INT, "count", "merge queries tried"),
    _f("vo.scale_check.{check}", N, "", "the network's view of the map's scale: checks, drift_max, drift_min"),
    # --- map and BA
    _f("map.points.{map_stage}", INT, "count", "map points after the front end, culling, BA"),
    _f("map.esi.{map_stage}", N, "", "scale-invariant error of the map's points against GT depth"),
    _f("map.outliers.{outliers}", N, "", "injected outliers: count, share culled, share dropped"),
    _f("map.inliers.kept", N, "", "share of clean points the culling kept"),
    _f("ba.runs", INT, "count", "culling + global BA runs"),
    _f("ba.requested", INT, "count", "global BAs Algorithm 1 requested"),
    _f("ba.points_dropped", INT, "count", "points the BAs dropped as outliers"),
    _f("ba.last.{ba_count}", INT, "count", "the last BA's problem sizes and iterations"),
    _f("ba.last.{ba_cost}", N, "", "the last BA's photometric cost: cost0 (before), cost (after)"),
    # --- adaptation
    _f("adaptation.steps", INT, "count", "optimiser steps"),
    _f("adaptation.keyframes_trained", INT, "count", "keyframes the network trained on"),
    _f("adaptation.keyframes_other_unit", INT, "count", "keyframes trained while in a map unit of their own"),
    _f("adaptation.training_keyframes", INT, "count", "keyframes with a training batch"),
    _f("adaptation.luo_keyframes_with_partner", INT, "count", "Luo-style keyframes with a partner frame"),
    _f("adaptation.labels", T, "", "what the labels could know: causal, hindsight or oracle"),
    _f("adaptation.pose_network", T, "", "scheme comoda: where its pose network came from"),
    _f("adaptation.l_val.{l_val}", N, "", "Algorithm 1's validations against τ"),
    _f("adaptation.reg.shrink.{agg}", N, "", "the regulariser's shrink factor over the parameters"),
    _f("adaptation.reg.importance.mean", N, "", "the regulariser's mean importance"),
    # --- loops
    _f("loop.{loop_count}", INT, "count", "loop candidates, accepted, rejected; loops closed right"),
    _f("loop.closed_rot_err_deg_max", N, "deg", "largest rotation error of a closed loop against GT"),
    _f("loop.recall.{recall}", INT, "count", "revisits in GT and how many were found, verified, closed, refused"),
    # --- timing
    _f("timing.total_s", N, "s", "wall time of the run"),
    _f("timing.stage_s.{stage}", N, "s", "wall time by stage; they add up to total_s"),
    _f("timing.vo_fps", N, "frames/s", "front-end frames per second"),
    _f("timing.depth_ms", N, "ms", "one depth prediction"),
    _f("timing.{finetune_ms}", N, "ms", "median optimiser step, keyframe, batch, consolidation"),
    _f("timing.{finetune_s}", N, "s", "all optimiser steps / consolidations"),
    _f("timing.ba_s", N, "s", "all culling + global BA"),
    _f("timing.l_val_s", N, "s", "all L_val validations"),
    _f("timing.online_scoring_s", N, "s", "scoring each frame with the model of its time"),
    _f("timing.online_refresh_s", N, "s", "of it, new weights into the OpenVINO predictor"),
    _f("timing.consolidate_vs_step", N, "", "median consolidation over median step"),
    _f("timing.step_ms.{step_stat}", N, "ms", "the optimiser steps' wall times: median, p90, p99, max (steps.csv)"),
    _f("timing.steps_over_median", N, "", "the steps' sum over steps × median step: 1 without a stall"),
    _f("timing.beyond_steps", N, "", "total_s / finetune_steps_s − 1"),
    # --- dense reconstruction
    _f("dense.{dense_prefix}{dense_score}.{model}", N, "m | %", "the mesh against GT's, under a scaling"),
    _f("dense.{per_frame_scaling}.{dense_stat}.{model}", N, "", "per-frame scale factors' statistics"),
    _f("dense.{dense_prefix}{mesh}.{dense_model}", INT, "count", "TSDF blocks, triangles, frames capped"),
    _f("dense.{dense_scale}.{model}", N, "", "the VO-to-metric scale (scale, metric_scale)"),
    _f("dense.{dense_count}", INT, "count", "block_cap, segments, frames, frames_reference"),
    _f("dense.{dense_figure}", N, "", "memory_cap_mb, sim3_scale, time_s"),
    _f("dense.source", T, "", "whose poses the meshes were fused along"),
    # --- external models (mslam eval-depth)
    _f("external.{setting}", T, "", "an external model's name, kind, file format, npz key, alignment, folder"),
    _f("external.scale", N, "", "the factor every stored prediction value was multiplied by"),
)


@cache
def _index() -> tuple[dict[str, Field], list[tuple[re.Pattern[str], Field]]]:
    exact: dict[str, Field] = {}
    open_: list[tuple[re.Pattern[str], Field]] = []
    for f in FIELDS:
        keys = f.keys()
        if keys:
            exact.update((k, f) for k in keys if k not in exact)
        elif "." in f.pattern.partition("{")[2]:
            raise SchemaError(f"summary schema: the open family {f.pattern!r} must be one level deep")
        else:
            open_.append((re.compile(f.regex()), f))
    return exact, open_


def field_of(key: str) -> Field | None:
    """The field a dotted key belongs to, ``None`` if the schema has no such key."""
    exact, open_ = _index()
    if key in exact:
        return exact[key]
    return next((f for rx, f in open_ if rx.fullmatch(key)), None)


def has_prefix(prefix: str) -> bool:
    """True when some key of the schema starts with ``prefix`` (a reader's ``dense.gt_scale.``…)."""
    exact, open_ = _index()
    heads = [f.pattern.split("{", 1)[0] for _, f in open_]
    return any(k.startswith(prefix) for k in exact) or any(h.startswith(prefix) or prefix.startswith(h) for h in heads)


def fits(kind: Kind, value: JSON) -> bool:
    """Whether a JSON value (not ``null``) is of a field's kind."""
    if kind == "flag":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if kind == "integer":
        return isinstance(value, int)
    if kind == "number":
        return isinstance(value, (int, float))
    if kind == "text":
        return isinstance(value, str)
    return isinstance(value, list) if kind == "list" else isinstance(value, dict)


def check(key: str, value: JSON, where: str = "summary.json") -> None:
    """Raise :class:`SchemaError` unless ``key`` is in the schema and ``value`` (JSON-safe) is ``null`` or of its
    kind. ``where`` names the file (or the writer) in the message."""
    f = field_of(key)
    if f is None:
        raise SchemaError(f"{where}: key {key!r} is not in summary schema version {SCHEMA_VERSION}")
    if value is not None and not fits(f.kind, value):
        raise SchemaError(f"{where}: {key} = {value!r} is not a {f.kind} (summary schema version {SCHEMA_VERSION})")


_JSON_TYPE = {"number": "number", "integer": "integer", "flag": "boolean", "text": "string", "list": "array",
              "object": "object"}


def json_schema() -> JSONObject:
    """The JSON Schema (draft 2020-12) of a version-2 ``summary.json``: nested objects, every leaf its kind or
    ``null``; open families as ``patternProperties``."""
    root: JSONObject = {"type": "object", "properties": {}, "additionalProperties": False}

    def node(parent: JSONObject, part: str) -> JSONObject:
        props = parent.setdefault("properties", {})
        assert isinstance(props, dict)
        child = props.setdefault(part, {"type": "object", "properties": {}, "additionalProperties": False})
        assert isinstance(child, dict)
        return child

    def leaf(f: Field) -> JSONObject:
        return {"type": [_JSON_TYPE[f.kind], "null"], "description": f"{f.doc}" + (f" [{f.unit}]" if f.unit else "")}

    exact, open_ = _index()
    for key, f in sorted(exact.items()):
        *path, last = key.split(".")
        parent = root
        for p in path:
            parent = node(parent, p)
        props = parent["properties"]
        assert isinstance(props, dict)
        props[last] = leaf(f)
    for rx, f in open_:  # one level deep (_index): a pattern of the last part of the key
        *path, _ = f.pattern.partition("{")[0].split(".")
        parent = root
        for p in path:
            parent = node(parent, p)
        pats = parent.setdefault("patternProperties", {})
        assert isinstance(pats, dict)
        pats[f"^{rx.pattern[len(re.escape('.'.join(path) + '.')) if path else 0:]}$"] = leaf(f)
    props = root["properties"]
    assert isinstance(props, dict)
    props["schema_version"] = {"const": SCHEMA_VERSION}
    props["notes"] = {"type": "object", "additionalProperties": {"type": "string"},
                      "description": "why a null value is null, by its dotted key"}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": f"mslam-summary-v{SCHEMA_VERSION}", "title": "mslam summary.json", **root}


def schema_text() -> str:
    """:func:`json_schema` as the text of ``summary.schema.json``."""
    return json.dumps(json_schema(), indent=1, sort_keys=True) + "\n"


if __name__ == "__main__":  # python -m mutualslam_cli.results.schema [FILE]: write the shipped JSON Schema
    (Path(sys.argv[1]) if len(sys.argv) > 1 else SCHEMA_FILE).write_text(schema_text())
