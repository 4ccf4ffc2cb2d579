"""The denoiser network and the ScenePrior bundle: shapes, slot equivariance, LoRA-readiness, sampling,
checkpoints and the shipped bedroom prior."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from agents.denoiser import (DenoiserConfig, SceneDenoiser, ScenePrior, atomic_torch_save,
                             timestep_embedding)
from iarcs_env import FloorPlan, get_room
from iarcs_env.scene import SceneBatch
from iarcs_env.stats import DatasetStats

from conftest import L_SHAPE

BEDROOM = get_room("bedroom")
LORA_TARGETS = ("q_proj", "k_proj", "v_proj", "out_proj")


def _randomised(net: nn.Module, seed: int = 0) -> nn.Module:
    """Zero-initialised gates make a fresh network output 0; give every weight a random value."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.2)
    return net.eval()


def _stats() -> DatasetStats:
    return DatasetStats("bedroom", [-3.0, 0.0, -3.0, 3.0, 2.6, 3.0], [0.05, 0.05, 0.05, 1.5, 1.3, 1.5],
                        object_count_histogram=[0, 1, 2, 3, 2, 1])


def _floors():
    return [FloorPlan.from_vertices([(0, 0), (4, 0), (4, 3), (0, 3)]), FloorPlan.from_vertices(L_SHAPE),
            FloorPlan.from_vertices([(-1, -2), (2, -2), (2, 2), (-1, 2)])]


def _tiny_prior(seed: int = 0) -> ScenePrior:
    torch.manual_seed(seed)
    prior = ScenePrior.create("bedroom", _stats(), "tiny")
    _randomised(prior.denoiser, seed)
    return prior


@pytest.mark.parametrize("room", ["bedroom", "livingroom"])
def test_output_shape_is_input_shape(room):
    spec = get_room(room)
    net = SceneDenoiser(DenoiserConfig.tiny(), spec.feature_dim)
    x = torch.randn(2, spec.max_objects, spec.feature_dim)
    eps = net(x, torch.tensor([3, 900]), torch.randn(2, 256, 4))
    assert eps.shape == x.shape
    assert torch.all(eps == 0)  # adaLN-Zero: a fresh network predicts no noise (loss starts at 1)


def test_permutation_equivariance_over_slots():
    net = _randomised(SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim))
    x = torch.randn(4, 12, BEDROOM.feature_dim)
    t, floor = torch.tensor([0, 10, 500, 999]), torch.randn(4, 256, 4)
    perm = torch.randperm(12, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        eps = net(x, t, floor)
        assert eps.abs().max() > 1e-3
        assert torch.allclose(net(x[:, perm], t, floor), eps[:, perm], atol=1e-5)
        # the floor points are a set too (max-pool)
        pts = torch.randperm(256)
        assert torch.allclose(net(x, t, floor[:, pts]), eps, atol=1e-5)


def test_floor_context_cache_and_unconditional_input():
    net = _randomised(SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim))
    x, t, floor = torch.randn(2, 12, BEDROOM.feature_dim), torch.tensor([5, 50]), torch.randn(2, 256, 4)
    with torch.no_grad():
        assert torch.allclose(net(x, t, floor_context=net.encode_floor(floor)), net(x, t, floor))
        assert torch.allclose(net(x, t), net(x, t, torch.zeros_like(floor)), atol=1e-5)
        assert not torch.allclose(net(x, t), net(x, t, floor))
        assert torch.allclose(net(x, torch.tensor(5)), net(x, torch.tensor([5, 5])))


def test_attention_is_lora_ready():
    net = SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim)
    names = [n for n, _ in net.named_modules()]
    for target in LORA_TARGETS:
        hits = [n for n in names if n.endswith(target)]
        assert len(hits) == 2 * net.config.num_layers, target  # self- and cross-attention per block
        assert all(isinstance(net.get_submodule(n), nn.Linear) for n in hits)
    assert not any(isinstance(m, nn.MultiheadAttention) for m in net.modules())


def test_peft_lora_changes_outputs_consistently_in_train_and_eval():
    peft = pytest.importorskip("peft")
    net = _randomised(SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim))
    x, t, floor = torch.randn(2, 12, BEDROOM.feature_dim), torch.tensor([5, 500]), torch.randn(2, 256, 4)
    with torch.no_grad():
        base = net(x, t, floor)
    model = peft.get_peft_model(net, peft.LoraConfig(r=4, lora_alpha=4, target_modules=list(LORA_TARGETS)))
    with torch.no_grad():
        for n, p in model.named_parameters():
            if "lora_B" in n:
                p.normal_(0, 0.1)
    model.eval()
    with torch.no_grad():
        eval_out = model(x, t, floor)
    model.train()
    train_out = model(x, t, floor)  # dropout is 0 in the tiny preset: same function, with grad
    assert not torch.allclose(eval_out, base, atol=1e-4)
    assert torch.allclose(eval_out, train_out, atol=1e-6)
    assert any(p.requires_grad for n, p in model.named_parameters() if "lora_" in n)


def test_presets():
    paper, small = DenoiserConfig.paper(), DenoiserConfig.small()
    assert (paper.num_layers, paper.width, paper.num_heads, paper.ff_dim, paper.dropout) == (8, 512, 4, 2048, 0.1)
    assert paper.pointnet == (4, 64, 64, 512, 64)
    assert small.width < paper.width
    net = SceneDenoiser(small, BEDROOM.feature_dim)
    assert net.num_parameters() < 4_000_000  # a few MB
    assert net.flops_per_scene(12) > 0
    with pytest.raises(ValueError, match="unknown model preset"):
        DenoiserConfig.from_preset("huge")
    with pytest.raises(ValueError, match="unknown denoiser field"):
        DenoiserConfig.from_preset("small", widht=3)
    with pytest.raises(ValueError, match="divisible"):
        DenoiserConfig(width=30, num_heads=4)


def test_timestep_embedding_distinguishes_steps():
    e = timestep_embedding(torch.tensor([0, 1, 999]), 32)
    assert e.shape == (3, 32) and not torch.allclose(e[0], e[1])


def test_sample_returns_valid_scenes_and_is_seeded():
    prior = _tiny_prior()
    floors = _floors()
    batch = prior.sample(floors, num_steps=5, generator=torch.Generator().manual_seed(0))
    assert isinstance(batch, SceneBatch) and batch.labels.shape == (3, 12)
    assert batch.labels.min() >= 0 and batch.labels.max() < BEDROOM.num_classes
    assert torch.isfinite(batch.translations).all() and (batch.half_sizes[batch.mask] > 0).all()
    for f in batch.floors:  # returned in the scene frame: centred on the floor's bounding box
        assert abs(f.centre).max() < 1e-9
    again = prior.sample(floors, num_steps=5, generator=torch.Generator().manual_seed(0))
    assert torch.equal(batch.labels, again.labels) and torch.equal(batch.translations, again.translations)
    chunked = prior.sample(floors, num_steps=5, generator=torch.Generator().manual_seed(0), batch_size=3)
    assert torch.equal(batch.labels, chunked.labels)
    assert len(batch.to_layouts()) == 3
    guided = prior.sample(floors, num_steps=5, generator=torch.Generator().manual_seed(0), guidance_scale=2.0)
    assert guided.labels.shape == (3, 12)


def test_save_load_round_trip_gives_identical_samples(tmp_path):
    prior = _tiny_prior(seed=4)
    path = prior.save(tmp_path / "prior.pt")
    loaded = ScenePrior.load(path)
    assert loaded.denoiser.config == prior.denoiser.config and loaded.spec == prior.spec
    assert loaded.stats.bounds_translations == prior.stats.bounds_translations
    a = prior.sample(_floors(), num_steps=4, generator=torch.Generator().manual_seed(7))
    b = loaded.sample(_floors(), num_steps=4, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a.labels, b.labels) and torch.equal(a.translations, b.translations)
    assert torch.equal(a.yaws, b.yaws)
    # float16 storage halves the file and loads back as float32
    half = ScenePrior.load(prior.save(tmp_path / "half.pt", half=True))
    assert next(half.denoiser.parameters()).dtype == torch.float32
    assert (tmp_path / "half.pt").stat().st_size < 0.7 * path.stat().st_size


def test_load_rejects_other_files_clearly(tmp_path):
    with pytest.raises(FileNotFoundError, match="no scene-prior checkpoint"):
        ScenePrior.load(tmp_path / "missing.pt")
    atomic_torch_save({"step": 3}, tmp_path / "state.pt")
    with pytest.raises(ValueError, match="not an iARCS scene-prior checkpoint"):
        ScenePrior.load(tmp_path / "state.pt")
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="not a readable"):
        ScenePrior.load(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError, match="iarcs pretrain"):
        ScenePrior.load_default("diningroom")


def test_shipped_bedroom_prior_loads_and_samples_valid_scenes():
    path = ScenePrior.default_path("bedroom")
    if not path.exists():
        pytest.skip(f"no shipped prior at {path}")
    assert path.stat().st_size < 10_000_000
    prior = ScenePrior.load_default("bedroom")
    assert prior.spec.name == "bedroom" and prior.denoiser.config == DenoiserConfig.small()
    floors = _floors() * 3
    batch = prior.sample(floors, num_steps=20, generator=torch.Generator().manual_seed(0))
    counts = batch.mask.sum(1)
    assert (counts >= 1).all() and (counts <= 12).all()
    # a trained prior puts objects inside the room's bounds and makes beds
    labels = [BEDROOM.vocabulary[i] for i in batch.labels[batch.mask].tolist()]
    assert any(lbl.endswith("bed") for lbl in labels)
    inside = []
    for i, floor in enumerate(batch.floors):
        xmin, zmin, xmax, zmax = floor.bounds
        t = batch.translations[i][batch.mask[i]]
        inside.append((t[:, 0] > xmin - 0.3) & (t[:, 0] < xmax + 0.3) & (t[:, 2] > zmin - 0.3) & (t[:, 2] < zmax + 0.3))
    assert torch.cat(inside).float().mean() > 0.8  # object centres near or inside the floor's bounding box


def test_environment_default_stats_are_the_shipped_priors():
    from pathlib import Path

    import iarcs_env

    path = Path(iarcs_env.__file__).parent / "data" / "stats" / "bedroom.json"
    if not ScenePrior.default_path("bedroom").exists() or not path.exists():
        pytest.skip("no shipped bedroom prior or environment statistics")
    prior, stats = ScenePrior.load_default("bedroom"), DatasetStats.load(path)
    assert stats.bounds_translations == pytest.approx(prior.stats.bounds_translations)
    assert stats.bounds_sizes == pytest.approx(prior.stats.bounds_sizes)
