"""RangeRet networks: published fixtures, checkpoint loading and its errors, the thesis model and its
ablations, the decay cache, the fast token-mixing paths against the plain formulas, and the choice
among them."""

from __future__ import annotations

import hashlib
import logging
import math
import time
from pathlib import Path

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from rangeret.models import (
    CheckpointError,
    ModelConfig,
    build_model,
    list_models,
    load_checkpoint,
    save_checkpoint,
)
from rangeret.models.blocks import decay as decay_module
from rangeret.models.blocks import kernels
from rangeret.models.blocks import token_mixing as mixing
from rangeret.models.blocks.decay import (
    DECAYS,
    GridCache,
    decay_rates,
    distance_table,
    expand_table,
    grid_distance,
)
from rangeret.models.blocks.retention import MultiScaleRetention
from tests.support.paths import load_vectors

CIR_PARAMETERS = 3_761_876
THESIS_PARAMETERS = 1_699_220


def num_parameters(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@pytest.fixture(scope="module")
def small_fixture() -> dict:
    return load_vectors("rangeret-cir-32x256-2block.pt")


@pytest.fixture(scope="module")
def small_file(small_fixture, tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("published") / "cir-small.pt"
    torch.save(small_fixture["state_dict"], path)
    return str(path)


def randomise(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Random weights and BatchNorm statistics, so that every parameter matters in a comparison."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if tensor.is_floating_point():
                values = (
                    torch.rand(tensor.shape, generator=gen) * 0.5 + 0.75
                    if "running_var" in name
                    else (torch.randn(tensor.shape, generator=gen) * 0.1)
                )
                tensor.copy_(values)
    return model


# --- the released network against the published code's output ------------------------------


def test_cir_reproduces_small_fixture_from_bare_state_dict(small_fixture, small_file):
    model = load_checkpoint(small_file, height=32, width=256)
    assert model.config.name == "rangeret-cir" and model.config.layers == 2
    assert not model.training
    assert num_parameters(model) == small_fixture["num_parameters"]
    with torch.inference_mode():
        out = model(small_fixture["input"])
    expected = small_fixture["logits"].permute(0, 3, 1, 2)
    assert out.shape == expected.shape == (1, 20, 32, 256)
    assert (out - expected).abs().max().item() <= 2e-4
    info = model.checkpoint_info
    assert info.published and info.name == "rangeret-cir"
    assert info.sha256 == hashlib.sha256(Path(small_file).read_bytes()).hexdigest()
    assert info.config["height"] == 32 and info.config["width"] == 256


def test_cir_reproduces_kitti_fixture_from_wrapped_state_dict(tmp_path):
    release = build_model("rangeret-cir", 64, 1024).state_dict()  # the release's 8-block shape
    path = tmp_path / "rangeret-kitti.pt"
    torch.save({"model_state_dict": release, "epoch": 3}, path)
    model = load_checkpoint(path)
    assert model.config.layers == 8 and (model.config.height, model.config.width) == (64, 1024)
    assert num_parameters(model) == CIR_PARAMETERS
    fixture = load_vectors("rangeret-cir-64x1024-1block.pt")
    torch.save({"model_state_dict": fixture["state_dict"], "epoch": 3}, path)
    model = load_checkpoint(path)
    assert model.config.layers == 1 and (model.config.height, model.config.width) == (64, 1024)
    with torch.inference_mode():
        out = model(fixture["input"])
    at_pixels = out.flatten(2)[0, :, fixture["pixels"]].T
    assert (at_pixels - fixture["logits_at_pixels"]).abs().max().item() <= 2e-4
    assert torch.equal(out.argmax(1), fixture["argmax"].long())


def test_cir_parameter_count_and_names():
    assert num_parameters(build_model("rangeret-cir")) == CIR_PARAMETERS
    assert list_models() == ["rangeret-cir", "rangeret-thesis"]


# --- loading errors ---------------------------------------------------------------------------


def save_state(tmp_path, state, name="bad.pt") -> str:
    path = tmp_path / name
    torch.save(state, path)
    return str(path)


def test_missing_key_is_named(small_fixture, tmp_path):
    state = dict(small_fixture["state_dict"])
    del state["backbone.ffns.1.fc2.bias"]
    with pytest.raises(CheckpointError, match=r"missing keys \(1\): backbone\.ffns\.1\.fc2\.bias"):
        load_checkpoint(save_state(tmp_path, state), height=32, width=256)


def test_truncated_state_dict_names_keys_and_what_the_file_fits(small_fixture, tmp_path):
    keys = list(small_fixture["state_dict"])
    state = {k: small_fixture["state_dict"][k] for k in keys[: len(keys) // 2]}
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(save_state(tmp_path, state))
    message = str(err.value)
    assert (
        f"missing keys (151): {keys[len(state)]}" in message
        and "rangeret-cir with no blocks" in message
    )
    assert "rangeret-cir" in message and "64x1024" in message


def test_unexpected_key_is_named(small_fixture, tmp_path):
    state = {**small_fixture["state_dict"], "backbone.extra.weight": torch.zeros(3)}
    with pytest.raises(CheckpointError, match=r"unexpected keys \(1\): backbone\.extra\.weight"):
        load_checkpoint(save_state(tmp_path, state), height=32, width=256)


def test_misshaped_key_is_named_with_both_shapes(small_fixture, tmp_path):
    state = {**small_fixture["state_dict"], "head.mlp1.weight": torch.zeros(64, 96)}
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(save_state(tmp_path, state), height=32, width=256)
    message = str(err.value)
    assert "head.mlp1.weight (64, 96) in the file, (64, 128) in the network" in message
    assert "rangeret-cir with 2 blocks" in message


def test_wrong_model_name_says_what_the_file_fits(small_file):
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(small_file, model="rangeret-thesis", height=32, width=256)
    message = str(err.value)
    assert "rem.conv_block.0.conv1.weight" in message and "rem.blocks.0.conv.weight" in message
    assert "fit rangeret-cir with 2 blocks" in message


def test_unknown_model_name(small_file):
    with pytest.raises(CheckpointError, match="rangeret-nope"):
        load_checkpoint(small_file, model="rangeret-nope")
    with pytest.raises(ValueError, match="known models: rangeret-cir, rangeret-thesis"):
        build_model("rangeret-nope")


def test_keys_that_fit_neither_network(tmp_path):
    path = save_state(tmp_path, {"encoder.weight": torch.zeros(2, 2)})
    with pytest.raises(CheckpointError, match="fit neither network"):
        load_checkpoint(path)


def test_non_checkpoint_files_are_named(tmp_path):
    text = tmp_path / "notes.pt"
    text.write_bytes(b"this is not a checkpoint")
    with pytest.raises(CheckpointError, match=r"notes\.pt is not a RangeRet checkpoint"):
        load_checkpoint(text)
    listing = save_state(tmp_path, [torch.zeros(1)], "list.pt")
    with pytest.raises(CheckpointError, match=r"list\.pt holds neither a state_dict"):
        load_checkpoint(listing)


# --- the project's own checkpoints ------------------------------------------------------------


@pytest.mark.parametrize("name", ["rangeret-thesis", "rangeret-cir"])
def test_own_checkpoint_round_trip(name, tmp_path):
    model = randomise(
        build_model(name, height=16, width=128, num_classes=5, layers=2, decay="manhattan")
    ).eval()
    labels = {"name": "toy", "learning_map": {0: 0, 10: 1}, "names": ["unlabeled", "car"]}
    projection = {"height": 16, "width": 128, "fov_up": 3.0, "fov_down": -25.0}
    metadata = {"epoch": 7, "miou": 0.42, "history": [0.1, 0.2], "simulated": True}
    path = tmp_path / "nested" / "best.pt"
    digest = save_checkpoint(
        path, model, label_config=labels, projection=projection, metadata=metadata
    )
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    assert torch.load(path, weights_only=True)["model"] == name

    loaded = load_checkpoint(path)
    assert loaded.config == model.config and not loaded.training
    x = torch.randn(2, 5, 16, 128)
    with torch.inference_mode():
        assert torch.equal(loaded(x), model(x))
    info = loaded.checkpoint_info
    assert (info.name, info.sha256, info.published) == (name, digest, False)
    assert info.config == model.config.to_dict() and info.config["decay"] == "manhattan"
    assert (info.label_config, info.projection, info.metadata) == (labels, projection, metadata)


def test_own_checkpoint_refuses_another_resolution_or_configuration(tmp_path):
    path = tmp_path / "thesis.pt"
    save_checkpoint(path, build_model("rangeret-thesis", height=32, width=256, layers=1))
    assert (
        load_checkpoint(path, model="rangeret-thesis", height=32, width=256, layers=1).config.layers
        == 1
    )
    with pytest.raises(
        CheckpointError,
        match=r"records rangeret-thesis at 32x256.*height 64 requested, 32 recorded",
    ):
        load_checkpoint(path, height=64, width=1024)
    with pytest.raises(
        CheckpointError, match="decay 'bidirectional' requested, 'exp-manhattan' recorded"
    ):
        load_checkpoint(path, decay="bidirectional")
    with pytest.raises(CheckpointError, match="model 'rangeret-cir' requested"):
        load_checkpoint(path, model="rangeret-cir")


def test_save_refuses_records_that_are_not_plain(tmp_path):
    model = build_model("rangeret-thesis", height=16, width=128, layers=1)
    with pytest.raises(TypeError, match=r"metadata\['when'\] is a object"):
        save_checkpoint(tmp_path / "x.pt", model, metadata={"when": object()})


# --- the thesis network and its ablations -----------------------------------------------------


def test_thesis_parameter_count_at_64x1024():
    model = build_model("rangeret-thesis")
    assert num_parameters(model) == THESIS_PARAMETERS
    assert abs(THESIS_PARAMETERS - 1.69e6) / 1.69e6 < 0.01
    assert model.config.grid == (15, 255)


@pytest.mark.parametrize(("height", "width"), [(16, 128), (32, 256), (64, 512), (7, 7)])
def test_thesis_output_shapes(height, width):
    model = build_model("rangeret-thesis", height=height, width=width).eval()
    with torch.inference_mode():
        out = model(torch.randn(2, 5, height, width))
    assert out.shape == (2, 20, height, width) and torch.isfinite(out).all()


@pytest.mark.slow
def test_thesis_output_shapes_at_sensor_resolutions():
    for width in (1024, 2048):
        model = build_model("rangeret-thesis", height=64, width=width).eval()
        with torch.inference_mode():
            out = model(torch.randn(1, 5, 64, width))
        assert out.shape == (1, 20, 64, width) and torch.isfinite(out).all()


ABLATIONS = [
    {"mixer": "attention"},
    *({"decay": d} for d in DECAYS),
    {"rem": "linear"},
    {"residual": False},
    {"patch_size": 4, "stride": 4},
    {"patch_size": (2, 8), "stride": (2, 8)},
    {"layers": 2, "heads": 8, "dim": 64},
]


@pytest.mark.parametrize(
    "overrides", ABLATIONS, ids=lambda o: "-".join(f"{k}={v}" for k, v in o.items())
)
@pytest.mark.parametrize("name", ["rangeret-thesis", "rangeret-cir"])
def test_each_switch_builds_and_runs(name, overrides):
    model = build_model(name, height=16, width=128, num_classes=7, **overrides).eval()
    for key, value in overrides.items():
        expected = (
            (value, value) if key in ("patch_size", "stride") and isinstance(value, int) else value
        )
        assert getattr(model.config, key) == expected
    with torch.inference_mode():
        out = model(torch.randn(1, 5, 16, 128))
    assert out.shape == (1, 7, 16, 128) and torch.isfinite(out).all()


def test_switches_change_the_structure_the_thesis_describes():
    keys = set(build_model("rangeret-thesis", mixer="attention").state_dict())
    assert "backbone.retentions.0.g_proj.weight" not in keys
    assert "backbone.retentions.0.group_norm.weight" not in keys
    assert "rem.blocks.0.linear.weight" in set(
        build_model("rangeret-thesis", rem="linear").state_dict()
    )
    assert num_parameters(build_model("rangeret-thesis", mixer="attention")) == 1_566_100
    with pytest.raises(ValueError, match="attention"):
        build_model("rangeret-thesis", mixer="attention", decay="manhattan")
    with pytest.raises(ValueError, match="unknown overrides colour"):
        build_model("rangeret-thesis", colour="red")
    with pytest.raises(ValueError, match="holds no 7x7 patch"):
        build_model("rangeret-thesis", height=6, width=64)
    assert (
        ModelConfig.from_dict(build_model("rangeret-cir").config.to_dict()).name == "rangeret-cir"
    )


def test_gradients_reach_every_parameter():
    for name in ("rangeret-thesis", "rangeret-cir"):
        model = build_model(name, height=16, width=64, layers=2).train()
        model(torch.randn(2, 5, 16, 64)).square().mean().backward()
        unused = (
            {n for n, _ in model.named_parameters() if n.endswith("g_proj.weight")}
            if name == "rangeret-cir"
            else set()
        )
        for param_name, param in model.named_parameters():
            if param_name in unused:
                assert param.grad is None
            else:
                assert param.grad is not None and param.grad.abs().sum() > 0, param_name


def test_eval_mode_keeps_autograd_working():
    model = randomise(build_model("rangeret-cir", height=16, width=64, layers=1)).eval()
    x = torch.randn(1, 5, 16, 64)
    with torch.no_grad():
        expected = model(x)
    out = model(x)
    out.sum().backward()
    assert torch.allclose(out, expected, atol=1e-5)
    assert model.rem.conv_block[0].conv2.weight.grad is not None


def test_same_input_gives_the_same_output():
    model = randomise(build_model("rangeret-cir", height=32, width=128, layers=2)).eval()
    x = torch.randn(1, 5, 32, 128)
    with torch.inference_mode():
        assert torch.equal(model(x), model(x))


# --- the decay cache --------------------------------------------------------------------------


def test_decay_tables_are_not_in_the_state_dict():
    model = build_model("rangeret-thesis", height=16, width=128).eval()
    before = dict(model.state_dict())
    with torch.inference_mode():
        model(torch.randn(1, 5, 16, 128))
    after = model.state_dict()
    assert set(after) == set(before)
    assert not any("cache" in k or "decay" in k for k in after)
    assert len(model.backbone.cache.entries()) > 0


def test_decay_tables_are_built_once_per_shape_and_shared(monkeypatch):
    builds, tables = [], []
    real_table, real_tiled = decay_module.distance_table, mixing.retention_tiled

    def counting_table(*args):
        builds.append(args)
        return real_table(*args)

    def recording_tiled(q, k, v, table, norm, grid, tile=mixing.TILE):
        tables.append((table, norm))
        return real_tiled(q, k, v, table, norm, grid, tile)

    monkeypatch.setattr(decay_module, "distance_table", counting_table)
    monkeypatch.setattr(mixing, "retention_tiled", recording_tiled)
    model = build_model("rangeret-thesis", height=16, width=128).eval()
    with torch.inference_mode():
        model(torch.randn(1, 5, 16, 128))
        model(torch.randn(1, 5, 16, 128))
    assert len(tables) == 2 * model.config.layers
    assert all(t is tables[0][0] and n is tables[0][1] for t, n in tables)
    assert len(builds) == 2  # the decay table and its row norms, once each
    with torch.inference_mode():
        model(torch.randn(1, 5, 32, 128))  # another grid: built once more
    assert len(builds) == 4 and tables[-1][0].shape != tables[0][0].shape


def test_decay_tables_follow_the_module():
    model = randomise(build_model("rangeret-thesis", height=16, width=64, layers=2)).eval()
    x = torch.randn(1, 5, 16, 64)
    with torch.no_grad():
        expected = model(x)
    assert {key[3] for key in model.backbone.cache.entries()} == {torch.float32}
    model.to(torch.float64)
    assert model.backbone.cache.entries() == {}
    with torch.no_grad():
        out = model(x.double())
    assert out.dtype == torch.float64
    assert (out.float() - expected).abs().max() < 1e-4
    assert {key[3] for key in model.backbone.cache.entries()} == {torch.float64}

    model.to("meta")
    assert model.backbone.cache.entries() == {}
    with torch.no_grad():
        out = model(torch.empty(1, 5, 16, 64, dtype=torch.float64, device="meta"))
    assert out.device.type == "meta" and out.shape == (1, 20, 16, 64)
    assert all(t.device.type == "meta" for t in model.backbone.cache.entries().values())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    x = torch.randn(1, 5, 32, 256)
    for name in ("rangeret-thesis", "rangeret-cir"):
        model = randomise(build_model(name, height=32, width=256, layers=2)).eval()
        with torch.inference_mode():
            expected = model(x)
            model.cuda()
            out = model(x.cuda())
            with torch.autocast("cuda", dtype=torch.float16):
                half = model(x.cuda())
        assert (out.cpu() - expected).abs().max() < 1e-3
        assert torch.isfinite(half).all() and half.shape == expected.shape


# --- decay matrices and token mixing: fast forms against the plain formulas ---------------------

GRIDS = [(1, 1), (1, 6), (4, 1), (3, 7), (4, 10)]


@pytest.mark.parametrize("decay", DECAYS)
@pytest.mark.parametrize("grid", GRIDS)
def test_distance_table_holds_the_full_matrix(decay, grid):
    assert torch.equal(
        expand_table(distance_table(decay, *grid), grid[0]), grid_distance(decay, *grid)
    )


def test_decay_definitions():
    assert torch.allclose(
        decay_rates(4),
        torch.tensor([1 - 1 / 32, 1 - 1 / 64, 1 - 1 / 128, 1 - 1 / 256], dtype=torch.float64),
    )
    # tables hold g[c, j, c'] for query column c, key row offset j - (Hp - 1), key column c'
    circular = distance_table("circular", 15, 255)
    assert circular.max() == 3824
    # the circular distance wraps around the azimuth and is normalised by (Hp - 1) + floor(Wp / 2) = 141
    assert circular[0, 14, 254] == pytest.approx((1 / 141) ** 2 * 3824)
    assert circular[0, 28, 127] == 3824
    assert distance_table("exp-manhattan", 15, 255)[0, 28, 254] == 3824
    uni = grid_distance("unidirectional", 3, 4)
    assert uni[5, 2] == 3 and math.isinf(uni[2, 5])


def random_heads(grid, heads=3, dk=4, dv=6, batch=2, dtype=torch.float64, seed=0):
    gen = torch.Generator().manual_seed(seed)
    n = grid[0] * grid[1]
    return [torch.randn(batch, heads, n, d, generator=gen, dtype=dtype) for d in (dk, dk, dv)]


@pytest.mark.parametrize("decay", DECAYS)
def test_tiled_retention_equals_plain(decay):
    grid, heads = (4, 10), 3
    q, k, v = random_heads(grid, heads)
    cache = GridCache(decay, heads, 4)
    table = cache.get("decay_table", grid, q.device, torch.float64)
    norm = cache.get("decay_norm", grid, q.device, torch.float64)
    log_d = torch.log(decay_rates(heads))[:, None, None] * grid_distance(decay, *grid)
    plain = mixing.retention_plain(q, k, v, torch.exp(log_d))
    for tile in (3, 4, 128):
        assert torch.allclose(
            mixing.retention_tiled(q, k, v, table, norm, grid, tile), plain, atol=1e-12
        )
    full = cache.get("decay_full", grid, q.device, torch.float64)
    assert torch.allclose(mixing.retention_full(q, k, v, full), plain, atol=1e-12)
    q32, k32, v32 = (t.float() for t in (q, k, v))
    table32 = cache.get("decay_table", grid, q.device, torch.float32)
    norm32 = cache.get("decay_norm", grid, q.device, torch.float32)
    assert torch.allclose(
        mixing.retention_tiled(q32, k32, v32, table32, norm32, grid, 3), plain.float(), atol=1e-5
    )


@pytest.mark.parametrize("decay", DECAYS)
def test_tiled_softmax_equals_plain(decay):
    grid, heads = (4, 10), 3
    q, k, v = random_heads(grid, heads)
    cache = GridCache(decay, heads, 4)
    table = cache.get("bias_table", grid, q.device, torch.float64)
    bias = torch.log(decay_rates(heads))[:, None, None] * grid_distance(decay, *grid)
    plain = mixing.softmax_plain(q, k, v, bias)
    for tile in (3, 128):
        assert torch.allclose(mixing.softmax_tiled(q, k, v, table, grid, tile), plain, atol=1e-12)
    assert torch.allclose(
        mixing.softmax_fused(q, k, v, cache.get("bias_full", grid, q.device, torch.float64)),
        plain,
        atol=1e-12,
    )
    q32, k32, v32 = (t.float() for t in (q, k, v))
    table32 = cache.get("bias_table", grid, q.device, torch.float32)
    assert torch.allclose(
        mixing.softmax_tiled(q32, k32, v32, table32, grid, 3), plain.float(), atol=1e-5
    )


def test_tiled_forms_have_the_plain_gradients():
    grid, heads = (3, 7), 2
    cache = GridCache("circular", heads, 4)
    bias = torch.log(decay_rates(heads))[:, None, None] * grid_distance("circular", *grid)
    decay = torch.exp(bias)
    table_b = cache.get("bias_table", grid, torch.device("cpu"), torch.float64)
    table_d = cache.get("decay_table", grid, torch.device("cpu"), torch.float64)
    norm = cache.get("decay_norm", grid, torch.device("cpu"), torch.float64)
    forms = [
        (
            lambda q, k, v: mixing.softmax_tiled(q, k, v, table_b, grid, 4),
            lambda q, k, v: mixing.softmax_plain(q, k, v, bias),
        ),
        (
            lambda q, k, v: mixing.retention_tiled(q, k, v, table_d, norm, grid, 4),
            lambda q, k, v: mixing.retention_plain(q, k, v, decay),
        ),
    ]
    for tiled, plain in forms:
        grads = []
        for form in (tiled, plain):
            inputs = [t.requires_grad_() for t in random_heads(grid, heads, seed=1)]
            form(*inputs).sin().sum().backward()
            grads.append([t.grad for t in inputs])
        for a, b in zip(*grads, strict=True):
            assert torch.allclose(a, b, atol=1e-10)


def test_parallel_retention_equals_recurrent_with_unidirectional_decay():
    torch.manual_seed(0)
    grid = (3, 5)
    layer = MultiScaleRetention(dim=16, heads=2, value_factor=2).double()
    cache = GridCache("unidirectional", heads=2, key_dim=8)
    x = torch.randn(2, 15, 16, dtype=torch.float64)
    with torch.no_grad():
        parallel, recurrent = layer(x, grid, cache), layer.forward_recurrent(x, grid, cache)
    assert torch.allclose(parallel, recurrent, atol=1e-10)
    with pytest.raises(ValueError, match="unidirectional"):
        layer.forward_recurrent(x, grid, GridCache("circular", 2, 8))


# --- compute dtype, aligned matrices and the choice among exact forms --------------------------

#: Grids whose token count is not a multiple of 8, like 15 x 255 = 3825 at 64 x 1024.
ODD_GRIDS = [(3, 7), (5, 13), (4, 11)]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_cached_matrices_are_aligned_views_in_the_asked_dtype(dtype):
    grid, heads = (3, 7), 2
    cache = GridCache("circular", heads, 4)
    cpu = torch.device("cpu")
    log_d = torch.log(decay_rates(heads))[:, None, None] * grid_distance("circular", *grid)
    decay = torch.exp(log_d)
    expected = {"bias_full": log_d, "decay_full": decay / decay.sum(-1, keepdim=True).sqrt()}
    for kind, full in expected.items():
        entry = cache.get(kind, grid, cpu, dtype)
        assert entry.shape == (heads, 21, 21) and entry.dtype == dtype
        assert entry.stride() == (21 * 24, 24, 1)
        assert torch.allclose(entry.double(), full.to(dtype).double(), rtol=1e-12, atol=0)
    for kind in ("bias_table", "decay_table", "decay_norm"):
        assert cache.get(kind, grid, cpu, dtype).dtype == dtype


def test_fused_attention_reads_the_aligned_bias_without_a_copy():
    grid, heads = (3, 7), 2
    q, k, v = random_heads(grid, heads, dk=8, dv=16, dtype=torch.float32)
    bias = GridCache("circular", heads, 8).get("bias_full", grid, q.device, torch.float32)
    seen = []

    class Recorder(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            seen.append(func.__name__)
            return func(*args, **(kwargs or {}))

    with Recorder():
        out = mixing.softmax_fused(q, k, v, bias)
    assert not any(name.startswith(("constant_pad", "pad", "_to_copy", "clone")) for name in seen)
    assert torch.allclose(out, mixing.softmax_plain(q, k, v, bias), atol=1e-5)


@pytest.mark.parametrize("grid", ODD_GRIDS)
@pytest.mark.parametrize("decay", DECAYS)
def test_every_form_equals_plain_at_fp32_for_odd_token_counts(decay, grid):
    heads = 3
    q, k, v = random_heads(grid, heads, dk=4, dv=8, dtype=torch.float32, seed=2)
    cache = GridCache(decay, heads, 4)
    cpu = torch.device("cpu")
    log_d = torch.log(decay_rates(heads))[:, None, None] * grid_distance(decay, *grid)
    plain = mixing.retention_plain(q, k, v, torch.exp(log_d).float())
    forms = {
        "tiled": mixing.retention_tiled(
            q,
            k,
            v,
            cache.get("decay_table", grid, cpu, torch.float32),
            cache.get("decay_norm", grid, cpu, torch.float32),
            grid,
            5,
        ),
        "full": mixing.retention_full(q, k, v, cache.get("decay_full", grid, cpu, torch.float32)),
    }
    for name, out in forms.items():
        assert (out - plain).abs().max() < 1e-5, name
    plain = mixing.softmax_plain(q, k, v, log_d.float())
    forms = {
        "tiled": mixing.softmax_tiled(
            q, k, v, cache.get("bias_table", grid, cpu, torch.float32), grid, 5
        ),
        "fused": mixing.softmax_fused(q, k, v, cache.get("bias_full", grid, cpu, torch.float32)),
    }
    for name, out in forms.items():
        assert (out - plain).abs().max() < 1e-5, name


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("decay", DECAYS)
def test_flex_score_mod_equals_the_bias(decay):
    grid, heads = (5, 13), 3
    q, k, v = random_heads(grid, heads, dk=4, dv=8, dtype=torch.float32, seed=3)
    bias = torch.log(decay_rates(heads))[:, None, None] * grid_distance(decay, *grid)
    score_mod = mixing.decay_score_mod(decay, grid, heads, torch.device("cpu"))
    assert score_mod is mixing.decay_score_mod(decay, grid, heads, torch.device("cpu"))
    out = mixing.softmax_flex(q, k, v, score_mod)
    assert (out - mixing.softmax_plain(q, k, v, bias.float())).abs().max() < 1e-5


class WideDispatch(TorchDispatchMode):
    """Records the dtype of every op output with at least `numel` elements."""

    def __init__(self, numel: int) -> None:
        super().__init__()
        self.numel = numel
        self.dtypes: set[torch.dtype] = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in out if isinstance(out, (tuple, list)) else (out,):
            if isinstance(t, torch.Tensor) and t.numel() >= self.numel:
                self.dtypes.add(t.dtype)
        return out


@pytest.mark.parametrize("name", ["rangeret-thesis", "rangeret-cir"])
def test_bf16_passes_build_no_float32_token_matrices(name):
    model = randomise(build_model(name, height=16, width=64, layers=1)).eval()
    grid = model.config.grid
    n = grid[0] * grid[1]
    x = torch.randn(1, 5, 16, 64)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        model(x)  # builds the cache
        wide = WideDispatch(model.config.heads * n * n)
        with wide:
            out = model(x)
    assert torch.isfinite(out).all()
    assert wide.dtypes <= {torch.bfloat16}
    entries = model.backbone.cache.entries()
    assert {key[3] for key in entries if key[0] != "rotary"} == {torch.bfloat16}
    # the N x N forms that CUDA may choose keep to the compute dtype as well
    cache = model.backbone.cache
    q, k, v = random_heads(grid, 4, dk=32, dv=64, batch=1, dtype=torch.bfloat16)
    cpu = torch.device("cpu")
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        cache.get("decay_full" if "thesis" in name else "bias_full", grid, cpu, torch.bfloat16)
        wide = WideDispatch(4 * n * n)
        with wide:
            if "thesis" in name:
                decay = cache.get("decay_full", grid, cpu, torch.bfloat16)
                mixing.retention_full(q, k, v, decay)
            else:
                mixing.softmax_fused(q, k, v, cache.get("bias_full", grid, cpu, torch.bfloat16))
    assert wide.dtypes <= {torch.bfloat16}


@pytest.fixture
def measured_cpu(monkeypatch):
    """Choose forms by measurement on the CPU too, from a clean slate."""
    monkeypatch.setattr(kernels, "MEASURED", ("cpu",))
    kernels.forget()
    yield
    kernels.forget()


def test_choice_is_measured_once_checked_and_logged(measured_cpu, caplog):
    q, _, v = random_heads((3, 7), 2, dtype=torch.float32)
    reference = torch.ones(3)
    calls = {"slow": 0, "fast": 0}

    def slow():
        calls["slow"] += 1
        time.sleep(0.01)
        return reference

    def fast():
        calls["fast"] += 1
        return reference + 1e-7

    def inexact():
        return reference + 0.1

    def broken():
        raise RuntimeError("no kernel")

    candidates = {"slow": slow, "inexact": inexact, "broken": broken, "fast": fast}
    with caplog.at_level(logging.INFO, logger="rangeret.models.blocks.kernels"):
        assert kernels.choose("op", candidates, "slow", q, v) == "fast"
    assert "fast" in caplog.text and "inexact differs" in caplog.text
    assert "broken failed: RuntimeError" in caplog.text
    measured = dict(calls)
    assert kernels.run("op", candidates, "slow", q, v) is not reference
    assert calls == {"slow": measured["slow"], "fast": measured["fast"] + 1}
    assert list(kernels.choices().values()) == ["fast"]
    # without measurement the default runs
    kernels.forget()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(kernels, "MEASURED", ())
        assert kernels.choose("op", candidates, "slow", q, v) == "slow"
    assert kernels.choices() == {}


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("name", ["rangeret-thesis", "rangeret-cir"])
def test_measured_choice_keeps_the_logits(name, measured_cpu, monkeypatch):
    monkeypatch.setattr(mixing, "flex_available", lambda device: True)
    model = randomise(build_model(name, height=16, width=64, layers=2)).eval()
    x = torch.randn(1, 5, 16, 64)
    with torch.inference_mode():
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(kernels, "MEASURED", ())
            expected = model(x)
        out = model(x)
    names = set(kernels.choices().values())
    forms = {"full", "tiled"} if "thesis" in name else {"fused", "tiled", "flex"}
    assert len(kernels.choices()) == 1 and names <= forms
    assert (out - expected).abs().max() < 1e-4
