"""Where the network runs (mutualslam_cli/device.py), checked on any CPU: the setting's resolution, a grid's
GPU placement, and code that threads the device it is given.

There is no GPU in CI, so a device slip is caught the way a GPU would show it: every tensor made without an
explicit ``device=`` lands on the ``meta`` device (``torch.set_default_device``), where it has no data; the run
itself is told ``device=cpu``. Code that forgets the device then mixes a meta tensor with the run's CPU
tensors and fails, as a CPU tensor mixed with CUDA ones fails on a GPU. A static rule (no bare tensor
constructor in the library) catches the same slips before they run.
"""

from __future__ import annotations

import ast
import json
import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch
import yaml

from mutualslam_cli import ablate, device
from mutualslam_cli.adapt.buffer import KeyframeSample
from mutualslam_cli.adapt.inference import resolve_runtime
from mutualslam_cli.adapt.inputs import use_fast_path
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.config import CONFIG_DIR, AdaptConfig, RunConfig, load_config
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.pipeline import run_sequence
from mutualslam_cli.report.tables import build_tables, collect

LIBRARY = Path(__file__).resolve().parents[1] / "mutualslam_cli"


@contextmanager
def tensors_elsewhere_by_default():
    """Within the block a tensor made without ``device=`` is a ``meta`` tensor (module docstring)."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


def fake_gpus(monkeypatch, n: int, capability: tuple[int, int] = (9, 0)) -> None:
    """``torch.cuda`` as if ``n`` GPUs were there (nothing that runs kernels is faked)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: n > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: n)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda d=None: capability)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)


# --------------------------------------------------------------------------- resolution


def test_auto_is_the_cpu_without_cuda_and_cuda_fails_with_the_way_out(monkeypatch):
    fake_gpus(monkeypatch, 0)
    assert device.resolve_device("auto") == torch.device("cpu") == device.resolve_device("cpu")
    with pytest.raises(ConfigError, match=r"CUDA is not available.*device=cpu or auto"):
        device.resolve_device("cuda")
    for bad in ("gpu", "cuda:x", "CUDA", "", "cuda:0:1"):
        with pytest.raises(ConfigError, match="expected one of auto, cpu, cuda, cuda:N"):
            device.resolve_device(bad)
    with pytest.raises(ConfigError, match="device"):
        load_config(None, ["device=gpu"])
    assert load_config(None, ["device=cuda:3"]).device == "cuda:3"  # checked where it runs, not where it is set


def test_auto_picks_cuda_and_an_index_beyond_the_visible_gpus_is_refused(monkeypatch):
    fake_gpus(monkeypatch, 2)
    assert device.resolve_device("auto") == torch.device("cuda", 0)
    assert device.resolve_device("cuda") == torch.device("cuda", 0)
    assert device.resolve_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(ConfigError, match="sees 2 GPU"):
        device.resolve_device("cuda:2")


def test_precision_and_runtime_follow_the_device(monkeypatch):
    cuda = torch.device("cuda", 0)
    cfg = RunConfig()
    # OpenVINO is the CPU's fast path: on a GPU the evaluation runs the torch path there
    assert resolve_runtime("auto", "auto", cuda) == resolve_runtime("auto", "off", "cpu") == "torch"
    assert resolve_runtime("torch", "auto", cuda) == "torch"
    fake_gpus(monkeypatch, 1, capability=(8, 0))
    assert use_fast_path(cfg.net, cuda) is True  # tensor cores: mixed precision by default
    assert use_fast_path(load_config(None, ["net.fast=off"]).net, cuda) is False
    fake_gpus(monkeypatch, 1, capability=(6, 1))  # a GTX 1070: fp16 is slower than fp32 there
    assert use_fast_path(cfg.net, cuda) is False
    assert use_fast_path(load_config(None, ["net.fast=on"]).net, cuda) is True
    assert device.grad_scaler(torch.device("cpu"), True) is None  # bf16 / fp32 need no loss scaling


def test_a_result_names_its_device():
    info = device.describe_device(torch.device("cpu"))
    assert info["device"] == "cpu"
    assert info["device_type"] == "cpu"
    assert info["device_name"]
    assert device.device_label(info).startswith("cpu · ")
    assert device.device_label({"device_type": "cuda", "device_name": "NVIDIA H100"}) == "cuda · NVIDIA H100"
    assert device.configure(torch.device("cpu")) == {}  # cuDNN flags are a CUDA matter


# --------------------------------------------------------------------------- grids


def test_gpu_slots_one_gpu_per_worker(monkeypatch):
    fake_gpus(monkeypatch, 2)
    assert device.gpu_slots("auto", 2) == ["0", "1"] == device.gpu_slots("cuda", 2)
    assert device.gpu_slots("auto", 3) == ["0", "1", "0"]  # more workers than GPUs: round robin
    assert device.gpu_slots("cuda:1", 2) == []  # an explicit GPU for every job is kept
    assert device.gpu_slots("cpu", 2) == device.gpu_slots("auto", 1) == []
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")  # already narrowed: its names, not 0..n-1
    assert device.gpu_slots("auto", 2) == ["3", "5"]
    fake_gpus(monkeypatch, 0)
    assert device.gpu_slots("auto", 4) == []


def _visible_after_a_while() -> tuple[int, str | None]:
    time.sleep(0.3)  # keeps this worker busy so the next task goes to the other
    return os.getpid(), os.environ.get("CUDA_VISIBLE_DEVICES")


def test_each_pool_worker_sees_its_own_gpu():
    pool = ablate.make_pool(2, ["0", "1"])
    try:
        seen = dict(f.result() for f in [pool.submit(_visible_after_a_while) for _ in range(6)])
    finally:
        pool.shutdown()
    assert sorted(seen.values()) == ["0", "1"]
    assert len(seen) == 2


class _FakeFuture:
    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


class _FakeClient:
    """Records what the grid submits to Dask; runs nothing."""

    submitted: ClassVar[list[tuple[str, dict]]] = []

    def __init__(self, *_a, **_k) -> None:
        pass

    def submit(self, fn, *args, **kw):
        _FakeClient.submitted.append((fn.__name__, kw))
        return _FakeFuture(ablate.JobOutcome(args[1], "done") if fn is ablate._run_job else None)

    def scheduler_info(self):
        return {"workers": {}}

    def close(self):
        pass


class _FakeCluster:
    kwargs: ClassVar[dict] = {}

    def __init__(self, **kw) -> None:
        _FakeCluster.kwargs = kw

    def close(self) -> None:
        pass


@pytest.mark.parametrize(("spec", "wanted"), [("cuda", {"GPU": 1}), ("cuda:0", {"GPU": 1}), ("cpu", None),
                                          ("auto", None)])
def test_dask_jobs_ask_for_a_gpu_only_when_the_config_runs_on_cuda(monkeypatch, tmp_path, spec, wanted):
    distributed = pytest.importorskip("dask.distributed")
    monkeypatch.setattr(distributed, "Client", _FakeClient)
    monkeypatch.setattr(distributed, "LocalCluster", _FakeCluster)
    monkeypatch.setattr(distributed, "as_completed", lambda futs: iter(futs))
    _FakeClient.submitted = []
    cfg = load_config(None, [f"device={spec}"])
    jobs = ablate.expand(["seqA"], ["recent", "replay"], [0])
    out = list(ablate._dask_outcomes(cfg, jobs, str(tmp_path), None, None, 2, None))
    assert [o.status for o in out] == ["done", "done"]
    kinds = [(name, kw.get("resources")) for name, kw in _FakeClient.submitted]
    assert kinds == [("_prepare_one", None), ("_run_job", wanted), ("_run_job", wanted)]  # the front end: a CPU task
    assert _FakeCluster.kwargs["resources"] == wanted  # a LocalCluster's workers declare one GPU each


# --------------------------------------------------------------------------- the device threaded through


#: Tensor factories that take ``device=``; without it they make the tensor on the default device.
FACTORIES = {"zeros", "ones", "empty", "full", "arange", "linspace", "logspace", "eye", "rand", "randn", "randint",
             "randperm", "tensor", "as_tensor", "scalar_tensor", "empty_strided", "Generator"}


def bare_constructors(root: Path = LIBRARY) -> list[str]:
    """``path:line torch.<factory>(...)`` calls without ``device=`` in the library (``*_like`` and
    ``new_*`` inherit their device; ``torch.from_numpy`` is the CPU by definition)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in FACTORIES
                    and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"
                    and not any(k.arg == "device" for k in node.keywords)):
                found.append(f"{path.relative_to(root.parent)}:{node.lineno} torch.{node.func.attr}(...)")
    return found


def test_the_rule_finds_a_planted_bare_constructor(tmp_path):
    pkg = tmp_path / "mutualslam_cli"
    pkg.mkdir()
    (pkg / "m.py").write_text("import torch\na = torch.zeros(3)\nb = torch.ones(2, device=x)\n"
                              "c = torch.zeros_like(b)\nd = torch.tensor([1.0])\n")
    assert bare_constructors(pkg) == ["mutualslam_cli/m.py:2 torch.zeros(...)",
                                      "mutualslam_cli/m.py:5 torch.tensor(...)"]


def test_no_bare_tensor_constructor_in_the_library():
    """Every tensor the library makes names its device (``device=x.device``, ``device=self.device``, or
    ``device="cpu"`` where it is host data on purpose): on a GPU a bare one is a CPU tensor among CUDA ones."""
    found = bare_constructors()
    assert not found, "tensors made without device= (add device=...):\n" + "\n".join(found)


class _TinyNet(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.c1 = torch.nn.Conv2d(3, 4, 3, padding=1)
        self.c2 = torch.nn.Conv2d(4, 1, 3, padding=1)

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        return 1.0 / (0.1 + 5.0 * torch.sigmoid(self.c2(torch.relu(self.c1(x)))))


def _keyframes(n: int = 9, h: int = 32, w: int = 48) -> list[KeyframeSample]:
    g = torch.Generator(device="cpu").manual_seed(0)
    K = torch.tensor([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]])
    out = []
    for k in range(n):
        T = np.eye(4)
        T[:3, 3] = [0.05 * k, 0.0, 0.01 * k]
        uv = torch.rand(20, 2, generator=g) * torch.tensor([w - 1.0, h - 1.0])
        out.append(KeyframeSample(k, torch.rand(3, h, w, generator=g), K, T, uv, 1.0 + torch.rand(20, generator=g)))
    return out


@pytest.mark.parametrize(("scheme", "mode"), [("replay+ewc", "prox"), ("replay+mas", "penalty"), ("replay+si", "prox"),
                                          ("luo", "prox")])
def test_the_adapter_threads_its_device(scheme, mode):
    """Steps, EWC's Fisher, MAS's and SI's importance, L_val: the same numbers with every stray tensor elsewhere."""
    samples = _keyframes()

    def adapt(net: torch.nn.Module) -> tuple[list[float], dict[int, float]]:
        ad = OnlineAdapter(net, AdaptConfig(scheme=scheme, steps_per_keyframe=2, validate_every=3),
                           samples[0].K, seed=0, reg_mode=mode, device=torch.device("cpu"))
        for s in samples:
            ad.add_keyframe(s)
        assert ad.history[-1].t == len(samples) - 1
        assert any(i.trained for i in ad.history)
        return [p.detach().sum().item() for p in ad.net.parameters()], ad.per_keyframe_val_loss()

    torch.manual_seed(0)
    want = adapt(_TinyNet())
    torch.manual_seed(0)
    net = _TinyNet()  # built on the CPU as the library builds its networks, then handed over
    with tensors_elsewhere_by_default():
        got = adapt(net)
    assert got == want


@pytest.fixture(scope="module")
def runs_both_ways(tiny_run):
    """A tiny run (EWC, online scores, final BA with culling, evaluation, depth export, dense) as usual and with
    every stray tensor elsewhere."""
    tmp, seq = tiny_run
    sets = [f"net.weights={tmp / 'weights'}", "device=cpu", "ba.d_max=0.2", "ba.final=always", "dense.enabled=true"]
    plain = run_sequence(seq, load_config(CONFIG_DIR / "smoke.yaml", sets), out=tmp / "dev_plain")
    with tensors_elsewhere_by_default():
        threaded = run_sequence(seq, load_config(CONFIG_DIR / "smoke.yaml", sets), out=tmp / "dev_meta")
    return plain, threaded


def test_a_whole_run_threads_its_device_and_records_it(runs_both_ways):
    plain, threaded = runs_both_ways
    a, b = plain.summary.flat(), threaded.summary.flat()
    for key in ("depth.pcd.lsq.adapted", "depth.pcd.lsq.pretrained", "depth.pcd_online.lsq", "map.points.ba",
                "dense.fscore_5cm.adapted", "adaptation.steps"):
        assert a[key] == b[key], key
    man = json.loads((threaded.folder / "manifest.json").read_text())
    assert man["device"]["device"] == "cpu"
    assert man["device"]["device_name"]
    assert b["run.device"] == "cpu"
    assert b["run.device_label"].startswith("cpu · ")
    assert yaml.safe_load((threaded.folder / "config.yaml").read_text())["device"] == "cpu"


def test_reports_never_average_runs_of_different_devices(runs_both_ways, tmp_path):
    plain, _ = runs_both_ways
    for i, label in enumerate(("cpu · AVX2", "cuda · NVIDIA H100")):  # the same run, as if from two devices
        folder = tmp_path / "res" / "seq" / "replay+ewc" / f"seed{i}"
        folder.mkdir(parents=True)
        s = json.loads((plain.folder / "summary.json").read_text())
        s["seed"], s["run"]["device_label"] = i, label
        (folder / "summary.json").write_text(json.dumps(s))
        (folder / "config.yaml").write_text((plain.folder / "config.yaml").read_text())
    runs = collect([tmp_path / "res"])
    assert sorted(runs["config"]) == ["run_device=cpu · AVX2", "run_device=cuda · NVIDIA H100"]
    depth = build_tables(runs).tables["depth"]
    assert len(depth) == 2
    assert depth["seeds"].tolist() == [1, 1]


@pytest.mark.slow
def test_a_comoda_run_threads_its_device(tiny_run):
    # slow (~35 s in CI): CoMoDa's pose network and source bank, with every stray tensor elsewhere
    tmp, seq = tiny_run
    sets = [f"net.weights={tmp / 'weights'}", "device=cpu", "adapt.scheme=comoda"]
    with tensors_elsewhere_by_default():
        comoda = run_sequence(seq, load_config(CONFIG_DIR / "smoke.yaml", sets), out=tmp / "dev_comoda")
    assert comoda.summary.flat()["depth.pcd.lsq.adapted"] is not None
