"""The CPU record of runs and benchmarks: model, SIMD flags and the kind DESIGN §10 sets targets by."""

from __future__ import annotations

import pytest

from mutualslam_cli.bench.suite import _table, step_in_run, targets
from mutualslam_cli.machine import cpu_info, cpu_kind
from mutualslam_cli.results.run_folder import manifest


def _cpuinfo(flags: str) -> str:
    block = f"processor\t: 0\nmodel name\t: Some CPU\nflags\t\t: fpu {flags}\n"
    return block + "\n" + block.replace("processor\t: 0", "processor\t: 1")


@pytest.mark.parametrize(("flags", "kind"), [
    ("avx2 avx512f avx512_bf16 amx_tile amx_bf16 amx_int8", "AMX"),
    ("avx2 avx512f avx512_vnni avx512_bf16", "AVX512-BF16"),
    ("sse4_2 avx avx2 fma", "AVX2"),
    ("sse4_2", "other"),
])
def test_cpu_kind_from_cpuinfo(flags, kind):
    info = cpu_info(_cpuinfo(flags))
    assert info["cpu_model"] == "Some CPU"
    assert info["cpu_kind"] == kind
    assert set(info["cpu_flags"]) <= set(flags.split())
    assert cpu_kind(None) == "unknown"


def test_targets_follow_the_kind():
    assert targets("AMX")["predict_ms"] == ("<=", 15.0)
    assert targets("AMX")["finetune_ms"] == ("<=", 250.0)
    assert targets("AVX512-BF16")["predict_ms"] == ("<=", 40.0)
    assert targets("AVX512-BF16")["finetune_ms"][1] == 300
    assert "finetune_ms" not in targets("AVX2")
    assert targets("AVX2")["predict_ms"] == ("<=", 60.0)
    assert targets("other")["vo_fps"] == (">=", 60.0)
    assert targets("AMX")["finetune_run_ms"] == ("<=", 250.0)
    assert targets("AVX2")["finetune_run_vs_bench"][1] == 1.1


def test_the_step_inside_the_run_is_held_against_the_bench():
    res = {"cpu_kind": "AVX512-BF16", "finetune_fast_ms": 250.0, "finetune_run_ms": 290.0}
    res.update(step_in_run(res))
    assert res["finetune_run_vs_bench"] == pytest.approx(1.16)
    table = _table(res)
    assert "| step inside the run / step on the bench (×) | 1.16 | ≤ 1.1 | **no** |" in table
    assert "| fine-tuning step inside mslam run, replay+ewc, median (ms) | 290 | ≤ 300 | yes |" in table
    assert step_in_run({"finetune_fp32_ms": 500.0, "finetune_run_ms": 510.0})["finetune_run_vs_bench"] == 1.02
    assert step_in_run({"finetune_fast_ms": 250.0}) == {}


def test_every_run_records_its_cpu():
    m = manifest(["mslam", "run"], 0, {"total_s": 1.0})
    assert m["cpu_kind"] in ("AMX", "AVX512-BF16", "AVX2", "other", "unknown")
    assert m["cpu_count"] >= 1
    assert "cpu_flags" in m
    assert "cpu_model" in m


def test_onednn_kernels_are_read_by_isa_and_data_type():
    from mutualslam_cli.bench.kernels import parse_verbose

    head = "onednn_verbose,v1,primitive,exec,cpu,"
    lines = [head + "convolution,brg_conv_fwd:avx512_core_amx,forward_training,src:bf16:a:blocked:acdb::f0 wei:bf16,"
                    ",,mb2_ic64oc64,1.5",
             head + "convolution,brg_conv_bwd:avx512_core_amx+brg_conv_fwd:avx512_core_amx,backward_data,"
                    "src:bf16::blocked:acdb::f0,,,mb2,2.0",
             head + "convolution,jit_dw:avx512_core,forward_training,src:f32:ap:blocked:aBcd16b::f0,,,g9mb4,0.5",
             head + "reorder,jit:uni,undef,src:bf16::blocked:acdb::f0 dst:bf16,,,64x64x3x3,0.25",
             "onednn_verbose,v1,info,cpu,isa:Intel AVX-512 with AMX",
             "unrelated output"]
    k = parse_verbose(lines)
    assert k["convolutions"] == {"brg_conv_fwd:avx512_core_amx": 1, "jit_dw:avx512_core": 1,
                                 "brg_conv_bwd:avx512_core_amx+brg_conv_fwd:avx512_core_amx": 1}
    assert k["convolution_dtypes"] == {"bf16": 2, "f32": 1}
    assert k["convolution_ms"] == pytest.approx(4.0)
    assert k["reorder_ms"] == pytest.approx(0.25)
    table = _table({"cpu_kind": "AMX", "step_kernels": k})
    assert "avx512_core_amx ×2" in table
    assert "f32 ×1" in table
