"""The inference graph against the network it is built from: the published test vectors, every
configuration, with the CPU's fused kernels and without, bfloat16 agreement, and what building it
leaves alone."""

from __future__ import annotations

import pytest
import torch

from rangeret.inference.runtime.fast_graph import build_fast_graph, inference_graph
from rangeret.models import build_model, load_checkpoint
from rangeret.models.blocks import inference_forms
from rangeret.models.blocks import token_mixing as mixing
from rangeret.models.blocks.decay import GridCache
from rangeret.models.blocks.inference_forms import FastMixer
from tests.rangeret.models.test_networks import ABLATIONS, randomise
from tests.support.paths import load_vectors

#: The fp32 graph's largest difference from the network's logits.
FP32_TOLERANCE = 1e-4


@pytest.fixture(scope="module")
def small_fixture() -> dict:
    return load_vectors("rangeret-cir-32x256-2block.pt")


@pytest.fixture(scope="module")
def small_network(small_fixture, tmp_path_factory):
    path = tmp_path_factory.mktemp("published") / "cir-small.pt"
    torch.save(small_fixture["state_dict"], path)
    return load_checkpoint(path, height=32, width=256)


@pytest.mark.parametrize("fused", [True, False], ids=["cpu-kernels", "plain-ops"])
def test_fp32_graph_reproduces_the_small_fixture(small_fixture, small_network, fused):
    graph = build_fast_graph(small_network, fused=fused)
    assert graph.fused == fused
    with torch.inference_mode():
        out = graph(small_fixture["input"])
        plain = small_network(small_fixture["input"])
    assert out.dtype == torch.float32 and out.shape == plain.shape == (1, 20, 32, 256)
    assert (out - plain).abs().max().item() <= FP32_TOLERANCE
    assert (out - small_fixture["logits"].permute(0, 3, 1, 2)).abs().max().item() <= 2e-4


def test_fp32_graph_reproduces_the_kitti_fixture(tmp_path):
    fixture = load_vectors("rangeret-cir-64x1024-1block.pt")
    torch.save(fixture["state_dict"], tmp_path / "kitti.pt")
    network = load_checkpoint(tmp_path / "kitti.pt")
    with torch.inference_mode():
        out = build_fast_graph(network)(fixture["input"])
        plain = network(fixture["input"])
    assert (out - plain).abs().max().item() <= FP32_TOLERANCE
    at_pixels = out.flatten(2)[0, :, fixture["pixels"]].T
    assert (at_pixels - fixture["logits_at_pixels"]).abs().max().item() <= 2e-4
    assert torch.equal(out.argmax(1), fixture["argmax"].long())


@pytest.mark.parametrize("fused", [True, False], ids=["cpu-kernels", "plain-ops"])
@pytest.mark.parametrize(
    "overrides", ABLATIONS, ids=lambda o: "-".join(f"{k}={v}" for k, v in o.items())
)
@pytest.mark.parametrize("name", ["rangeret-thesis", "rangeret-cir"])
def test_fp32_graph_equals_the_network_in_every_configuration(name, overrides, fused):
    overrides = {"layers": 2, **overrides}
    network = randomise(build_model(name, height=16, width=128, num_classes=7, **overrides))
    network.eval()
    x = torch.randn(2, 5, 16, 128, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        out = build_fast_graph(network, fused=fused)(x)
        plain = network(x)
    assert out.shape == plain.shape == (2, 7, 16, 128)
    assert (out - plain).abs().max().item() <= FP32_TOLERANCE


def profiled(graph: torch.nn.Module, x: torch.Tensor) -> list:
    """The operator events of a second pass of `graph` (kernels' own operators included)."""
    with torch.inference_mode():
        graph(x)
        with torch.profiler.profile(record_shapes=True) as prof:
            graph(x)
    return list(prof.events())


def copied_shapes(events: list) -> set[tuple[int, ...]]:
    """The shapes of every tensor the events copy or convert."""
    copies = ("aten::copy_", "aten::_to_copy", "aten::clone")
    return {tuple(e.input_shapes[0]) for e in events if e.name in copies and e.input_shapes}


def attention_kernels(events: list) -> set[str]:
    """The attention kernels the events ran: the fused one or the math fallback."""
    return {e.name for e in events if e.name.startswith("aten::_scaled_dot_product_")}


def test_bf16_graph_holds_its_weights_in_bf16_and_agrees_with_fp32(small_fixture, small_network):
    graph = build_fast_graph(small_network, torch.bfloat16)
    weights = {name: b for name, b in graph.named_buffers() if b.dim() >= 2}
    float32 = {name for name, b in weights.items() if b.dtype == torch.float32}
    assert float32 == {"head.w2"}  # the last Linear (see FoldedHead)
    assert all(b.dtype == torch.bfloat16 for name, b in weights.items() if name not in float32)
    x = small_fixture["input"]
    events = profiled(graph, x)
    # no weight is cast or copied per pass, neither by the graph nor inside a kernel
    assert not copied_shapes(events) & {tuple(b.shape) for b in weights.values()}
    assert attention_kernels(events) == {"aten::_scaled_dot_product_flash_attention_for_cpu"}
    with torch.inference_mode():
        reference = small_network(x)
        out = graph(x)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    agree = (out.argmax(1) == reference.argmax(1)).float().mean().item()
    assert agree >= 0.99, agree


def test_building_the_graph_leaves_the_network_as_it_is(small_network, small_fixture):
    before = {k: v.clone() for k, v in small_network.state_dict().items()}
    graph = build_fast_graph(small_network, torch.bfloat16)
    assert graph.cache is small_network.backbone.cache
    with torch.inference_mode():
        graph(small_fixture["input"])
    after = small_network.state_dict()
    assert before.keys() == after.keys()
    assert all(
        torch.equal(before[k], after[k]) and before[k].dtype == after[k].dtype for k in before
    )
    grid = small_network.config.grid
    assert ("bias_full", grid, torch.device("cpu"), torch.bfloat16) in graph.cache.entries()
    with pytest.raises(ValueError, match="eval mode"):
        build_fast_graph(build_model("rangeret-cir", 32, 256, layers=1).train())


@pytest.mark.parametrize("decay", ["circular", "unidirectional"])
@pytest.mark.parametrize("grid", [(1, 1), (3, 7), (4, 10)])
def test_row_form_equals_the_plain_softmax(decay, grid):
    gen = torch.Generator().manual_seed(0)
    n = grid[0] * grid[1]
    q, k, v = (torch.randn(2, 4, n, d, generator=gen) for d in (8, 8, 16))
    cache = GridCache(decay, 4, 8)
    cpu = torch.device("cpu")
    table = cache.get("bias_table", grid, cpu, torch.float32)
    out = mixing.softmax_rows(q, k, v, table, grid)
    expected = mixing.softmax_plain(q, k, v, cache.get("bias_full", grid, cpu, torch.float32))
    assert out.shape == (2, n, 4, 16)
    assert (out - expected).abs().max().item() <= 1e-5


def test_bf16_graph_reads_the_bias_whole_or_by_rows(small_fixture, small_network, monkeypatch):
    x = small_fixture["input"]
    with torch.inference_mode():
        whole = build_fast_graph(small_network, torch.bfloat16)(x)
        monkeypatch.setattr(inference_forms, "FULL_BIAS_BYTES", 0)
        small_network.cpu()  # moving the network drops its cached decay
        rows_graph = build_fast_graph(small_network, torch.bfloat16)
        by_rows = rows_graph(x)
    fused = {"aten::_scaled_dot_product_flash_attention_for_cpu"}
    assert attention_kernels(profiled(rows_graph, x)) == fused
    kinds = {(key[0], key[3]) for key in small_network.backbone.cache.entries()}
    assert ("bias_table", torch.float32) in kinds and ("bias_full", torch.bfloat16) not in kinds
    assert (whole - by_rows).abs().max().item() <= 0.05
    assert (whole.argmax(1) == by_rows.argmax(1)).float().mean().item() >= 0.99


def test_which_runs_take_a_graph(small_network):
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert inference_graph(small_network, "bf16", cpu).dtype == torch.bfloat16
    assert inference_graph(small_network, "fp32", cpu) is None  # exact published labels
    assert inference_graph(small_network, "fp16", cpu) is None
    assert inference_graph(small_network, "bf16", cuda) is None  # autocast on CUDA, as before
    assert inference_graph(torch.nn.Conv2d(5, 20, 1), "bf16", cpu) is None
    mixers = [layer.mixer for layer in inference_graph(small_network, "bf16", cpu).layers]
    assert all(isinstance(m, FastMixer) and m.kind == "circular" for m in mixers)
