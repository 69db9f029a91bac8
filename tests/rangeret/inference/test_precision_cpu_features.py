"""The CPU as `--precision auto` and the speed card see it: model, the bf16 and VNNI flags of
`/proc/cpuinfo`, usable CPUs, torch's threads and capability."""

from __future__ import annotations

import torch

from rangeret.inference.runtime import cpu_features
from rangeret.inference.runtime.cpu_features import (
    FLAGS,
    CpuFeatures,
    parse_cpuinfo,
    torch_capability,
)

SAPPHIRE_RAPIDS = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R) Platinum 8480+
flags\t\t: fpu vme sse avx2 avx512f avx512_bf16 avx512_vnni avx_vnni amx_bf16 amx_tile amx_int8

processor\t: 1
model name\t: another name on a later processor
flags\t\t: fpu
"""

ZEN3 = """processor\t: 0
model name\t: AMD EPYC 7763 64-Core Processor
flags\t\t: fpu sse avx avx2 fma
"""

GRAVITON = """processor\t: 0
BogoMIPS\t: 243.75
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 bf16 i8mm
"""


def test_the_first_processor_gives_the_model_and_the_flags_that_matter():
    model, flags = parse_cpuinfo(SAPPHIRE_RAPIDS)
    assert model == "Intel(R) Xeon(R) Platinum 8480+"
    assert flags == {"avx2", "avx512_bf16", "avx512_vnni", "avx_vnni", "amx_bf16", "amx_tile"}
    assert parse_cpuinfo(ZEN3) == ("AMD EPYC 7763 64-Core Processor", frozenset({"avx2"}))
    assert parse_cpuinfo(GRAVITON) == (None, frozenset())
    assert parse_cpuinfo("") == (None, frozenset())


def test_native_bf16_is_amx_first_then_avx512_bf16():
    spr = CpuFeatures("spr", parse_cpuinfo(SAPPHIRE_RAPIDS)[1])
    assert spr.bf16_flag == "amx_bf16" and spr.has("avx512_vnni")
    assert CpuFeatures("cpx", frozenset({"avx512_bf16"})).bf16_flag == "avx512_bf16"
    assert CpuFeatures("zen3", frozenset({"avx2"})).bf16_flag is None
    text = spr.flags_text()
    assert text.startswith("AMX bf16 yes, AMX tiles yes, AVX-512 bf16 yes")
    assert CpuFeatures("zen3", frozenset({"avx2"})).flags_text().endswith("AVX-VNNI no, AVX2 yes")


def test_plain_data_names_every_flag():
    cpu = CpuFeatures("zen3", frozenset({"avx2"}), cpus=8, threads=4, capability="AVX2")
    assert cpu.to_dict() == {
        "model": "zen3",
        "flags": {flag: flag == "avx2" for flag in FLAGS},
        "cpus": 8,
        "torch_threads": 4,
        "torch_capability": "AVX2",
    }


def test_this_machine_is_read_once_and_agrees_with_torch(monkeypatch):
    here = cpu_features.cpu_features()
    assert here.model and here.cpus >= 1 and here.threads == torch.get_num_threads()
    assert here.capability == torch_capability()
    monkeypatch.setattr(cpu_features, "CPUINFO", cpu_features.Path("/nonexistent/cpuinfo"))
    assert cpu_features.cpu_features().flags == here.flags, "read once per process"
    cpu_features._cpuinfo.cache_clear()
    try:
        missing = cpu_features.cpu_features()
        assert missing.flags == frozenset() and missing.bf16_flag is None and missing.model
    finally:
        cpu_features._cpuinfo.cache_clear()
