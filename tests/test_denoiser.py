"""The denoiser network and the ScenePrior bundle: shapes, slot equivariance, LoRA-readiness, sampling,
checkpoints and the shipped bedroom prior."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from torch import nn

import agents.denoiser as denoiser_module
from agents.denoiser import (RETIRED_FIELDS, DenoiserConfig, SceneDenoiser, ScenePrior, atomic_torch_save,
                             timestep_embedding)
from iarcs_env import FloorPlan, get_room
from iarcs_env.scene import Layout, SceneBatch
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
        # the point tokens are every 32nd boundary point (tiny: 8 of 256) and attention ignores their order:
        # starting the boundary 32 points later gives the same tokens
        assert torch.allclose(net(x, t, floor.roll(32, dims=1)), eps, atol=1e-5)
        assert not torch.allclose(net(x, t, floor.roll(1, dims=1)), eps, atol=1e-5)


def test_global_floor_feature_is_a_set_function():
    net = _randomised(SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim))
    floor, subset = torch.randn(2, 256, 4), torch.arange(8) * 32
    with torch.no_grad():  # max-pooled PointNet feature: any order of the points
        glob = net.floor_encoder.encode(floor, subset)[0]
        assert torch.allclose(net.floor_encoder.encode(floor[:, torch.randperm(256)], subset)[0], glob, atol=1e-5)


@pytest.mark.parametrize("tokens, points", [(2, 8), (0, 8), (2, 300)])
def test_floor_conditioning(tokens, points):
    """The context is the adaLN row + global and per-point tokens + the raw boundary points and the floor's
    half-extents packed in rows of width d; the floor changes the output, an all-zero floor is unconditional."""
    cfg = DenoiserConfig.from_preset("tiny", floor_tokens=tokens, floor_point_tokens=points)
    net = _randomised(SceneDenoiser(cfg, BEDROOM.feature_dim))
    floor = torch.randn(2, 256, 4)
    ctx = net.encode_floor(floor)
    assert ctx.shape == (2, 1 + tokens + points + -(-(4 * points + 2) // cfg.width), cfg.width)
    x, t = torch.randn(2, 12, BEDROOM.feature_dim), torch.tensor([5, 50])
    with torch.no_grad():
        assert torch.allclose(net(x, t), net(x, t, torch.zeros_like(floor)), atol=1e-5)
        assert not torch.allclose(net(x, t), net(x, t, floor))
    assert net.flops_per_scene(12, include_floor=True) > net.flops_per_scene(12)
    with pytest.raises(ValueError, match="floor_point_tokens must be > 0"):
        DenoiserConfig(floor_point_tokens=0)
    with pytest.raises(ValueError, match="floor_tokens must be >= 0"):
        DenoiserConfig(floor_tokens=-1)


def test_wall_features_measure_the_nearest_walls():
    """A slot at (0.5, 0.25) in the square [-1, 1]^2 (walls sampled every 0.25): nearest wall x = 1 (inward
    normal -x, 0.5 inside), then the wall z = 1 (normal -z, 0.75 inside)."""
    net = SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim)
    s = torch.linspace(-1, 1, 9)
    one = torch.ones_like(s)
    walls = [torch.stack([s, -one, 0 * one, one], -1), torch.stack([one, s, -one, 0 * one], -1),
             torch.stack([-s, one, 0 * one, -one], -1), torch.stack([-one, -s, one, 0 * one], -1)]
    points = torch.cat(walls)[None]  # (1, 36, 4): x, z, nx, nz
    x = torch.zeros(1, 1, BEDROOM.feature_dim)
    x[0, 0, 0], x[0, 0, 2] = 0.5, 0.25  # room-frame translation x, z
    f = net.wall_features(x, points, torch.tensor([[1.0, 1.0]]))[0, 0]
    assert torch.allclose(f[:12], torch.tensor([-0.5, 0.0, -1.0, 0.0, 0.5, 0.0, -0.75, 0.0, -1.0, 0.75, 1.0, 1.0]),
                          atol=1e-6)
    # the same square scaled to half-extents (0.5, 0.25) gives the same features, in room units, plus the
    # half-extents; through forward's packed context, the extents come from the floor points
    extents = torch.tensor([[0.5, 0.25]])
    small = torch.cat([points[..., :2] * extents, points[..., 2:]], -1)
    f_room = net.wall_features(x, small, extents)[0, 0]
    assert torch.allclose(f_room[:12], torch.cat([f[:10], extents[0]]), atol=1e-6)
    # footprint-to-wall gaps (features taken as metres until set_metric_scale): a box of half size (0.1, 0.05)
    # at room-frame (0.5, 0.25) has free half-ranges (0.4, 0.2), so its centre is at (0.2, 0.05) m, 0.3 m from
    # the x wall and 0.2 m from the z wall, which its footprint reaches 0.1 and 0.05 m closer; turned by 90
    # degrees its axes swap: free ranges (0.45, 0.15), centre (0.225, 0.0375)
    x[0, 0, 3], x[0, 0, 5], x[0, 0, 6] = 0.1, 0.05, 1.0  # half size x, z; cos(yaw)
    assert torch.allclose(net.wall_features(x, small, extents)[0, 0, 12:], torch.tensor([0.2, 0.15]))
    x[0, 0, 6], x[0, 0, 7] = 0.0, 1.0
    assert torch.allclose(net.wall_features(x, small, extents)[0, 0, 12:], torch.tensor([0.225, 0.1125]))
    ctx = net.encode_floor(small)  # forward reads the extents back from the context, after 8 packed points
    assert torch.allclose(ctx[0, -2:].reshape(-1)[4 * 8:4 * 8 + 2], extents[0])


def test_room_frame_puts_walls_at_plus_minus_one():
    """A 4 m x 3 m room: a bed (half depth 0.9 m, turned to face -x) touching the +x wall has feature x = 1 in
    the room frame, whatever the sizes of room and bed, and 0.5 when its centre is halfway from the room's
    centre line to that position; decoding gives the metric positions back."""
    floor = FloorPlan.from_vertices([[0, 0], [4, 0], [4, 3], [0, 3]])
    lay = Layout("bedroom", floor, ["double_bed", "double_bed"], [[3.1, 0.5, 1.5], [2.55, 0.5, 1.5]],
                 [[1.0, 0.5, 0.9], [1.0, 0.5, 0.9]], [-1.5707963, -1.5707963])
    batch = SceneBatch.from_layouts([lay])
    room, dataset = _stats(), replace(_stats(), translation_frame="dataset")
    x = batch.encode(room)
    assert x[0, :2, 0].tolist() == pytest.approx([1.0, 0.5]) and x[0, 0, 2].item() == pytest.approx(0.0, abs=1e-6)
    assert x[0, 0, 0].item() != pytest.approx(batch.encode(dataset)[0, 0, 0].item())
    back = SceneBatch.decode(x, room, batch.floors)
    assert torch.allclose(back.translations, batch.translations, atol=1e-5)
    with pytest.raises(ValueError, match="half-extents"):
        SceneBatch(batch.spec, batch.labels, batch.translations, batch.half_sizes, batch.yaws, []).encode(room)
    with pytest.raises(ValueError, match="translation_frame"):
        ScenePrior(SceneDenoiser(DenoiserConfig.tiny(), BEDROOM.feature_dim), dataset)


def test_footprint_gap_through_the_feature_pipeline():
    """A bed whose foot end (half depth 0.9 m, turned to face -x) stops 2 cm short of the +x wall: the
    prior's wall features, computed from the encoded scene and floor condition, give a 0.02 m gap."""
    floor = FloorPlan.from_vertices([[0, 0], [4, 0], [4, 3], [0, 3]])
    lay = Layout("bedroom", floor, ["double_bed"], [[3.08, 0.5, 1.5]], [[1.0, 0.5, 0.9]], [-1.5707963])
    batch = SceneBatch.from_layouts([lay])
    prior = ScenePrior.create("bedroom", _stats(), "tiny")
    assert prior.denoiser.metric_bounds.tolist() == pytest.approx([-3.0, -3.0, 3.0, 3.0, 0.05, 0.05, 1.5, 1.5])
    x, f = batch.encode(prior.stats), prior.floor_condition(batch.floors).cpu()
    gaps = prior.denoiser.wall_features(x, f, f[..., :2].abs().amax(1))[0, 0, 12:]
    assert gaps[0].item() == pytest.approx(0.02, abs=1e-3)
    assert gaps[1].item() == pytest.approx(1.5 - 1.0, abs=1e-3)  # the z wall: 1.5 m away, half width 1.0 m


def test_floor_shape_reaches_every_layer_through_adaln():
    """The floor is in adaLN: the gates of every block depend on the floor."""
    net = _randomised(SceneDenoiser(DenoiserConfig.small(), BEDROOM.feature_dim))
    a, b = net.encode_floor(torch.randn(1, 256, 4)), net.encode_floor(torch.randn(1, 256, 4))
    assert not torch.allclose(a[:, 0], b[:, 0])


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


def test_cross_attention_without_projecting_the_context_matches_the_plain_layers(monkeypatch):
    """The cross-attention to the floor tokens with the key and value projections moved onto the queries gives the
    plain layers' output and gradients (float64, to rounding; the key bias, which the softmax drops, gets none).
    It runs only for more context tokens than queries and plain projections: a LoRA-wrapped key projection takes
    the plain path, so the adapter is applied."""
    peft = pytest.importorskip("peft")
    from agents.denoiser import Attention

    torch.manual_seed(0)
    att = _randomised(Attention(16, 4)).double()
    x, ctx = torch.randn(3, 5, 16, dtype=torch.float64), torch.randn(3, 9, 16, dtype=torch.float64)
    results = []
    for forward in (Attention.forward_reference, Attention.forward_context_absorbed):
        inputs = [x.clone().requires_grad_(True), ctx.clone().requires_grad_(True)]
        out = forward(att, *inputs)
        wrt = inputs + list(att.parameters())
        grads = torch.autograd.grad(out.square().sum(), wrt, allow_unused=True)
        results.append([out.detach()] + [torch.zeros_like(w) if g is None else g for g, w in zip(grads, wrt)])
    for a, b in zip(*results):
        assert torch.allclose(a, b, atol=1e-10)
    assert float(results[0][0].abs().max()) > 0.1  # not a trivially zero output

    calls = []
    absorbed = Attention.forward_context_absorbed
    monkeypatch.setattr(Attention, "forward_context_absorbed", lambda self, *a: calls.append(1) or absorbed(self, *a))
    assert torch.allclose(att(x, ctx), results[0][0], atol=1e-10) and len(calls) == 1
    att(x, ctx[:, :5])  # as many context tokens as queries: the plain path
    assert len(calls) == 1
    lora = peft.get_peft_model(nn.Sequential(att), peft.LoraConfig(r=2, target_modules=["k_proj"]))
    wrapped = lora.base_model.model[0]
    assert torch.allclose(wrapped(x, ctx), results[0][0], atol=1e-10)  # LoRA's B starts at zero
    assert len(calls) == 1


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
    assert paper == DenoiserConfig() and paper.floor_point_tokens == small.floor_point_tokens == 64
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


def test_load_rejects_other_files_clearly(tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="no scene-prior checkpoint"):
        ScenePrior.load(tmp_path / "missing.pt")
    atomic_torch_save({"step": 3}, tmp_path / "state.pt")
    with pytest.raises(ValueError, match="not an iARCS scene-prior checkpoint"):
        ScenePrior.load(tmp_path / "state.pt")
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="not a readable"):
        ScenePrior.load(tmp_path / "junk.pt")
    monkeypatch.setattr(denoiser_module, "CHECKPOINT_DIR", tmp_path)  # an installation without shipped priors
    with pytest.raises(FileNotFoundError, match="iarcs pretrain --config experiments/pretrain_diningroom.yaml"):
        ScenePrior.load_default("diningroom")
    # weights that do not fit the config (e.g. from an incompatible iARCS version): a clear error
    state = _tiny_prior().state()
    state["denoiser_config"]["floor_tokens"] = 3
    atomic_torch_save(state, tmp_path / "mismatch.pt")
    with pytest.raises(ValueError, match="do not fit"):
        ScenePrior.load(tmp_path / "mismatch.pt")


@pytest.mark.parametrize("key, value", [("room_frame", False), ("pair_bias", True), ("floor_adaln", False),
                                        ("floor_slot_features", False), ("floor_point_tokens", 0)])
def test_switches_of_earlier_designs_load_at_the_shipped_values_only(tmp_path, key, value):
    """A saved config naming the retired switches at the shipped checkpoints' values loads (they are ignored);
    another value is an earlier design, refused in one line that names the key; run settings likewise."""
    prior = _tiny_prior(seed=2)
    state = prior.state()
    state["denoiser_config"].update(RETIRED_FIELDS)
    atomic_torch_save(state, tmp_path / "shipped.pt")
    assert ScenePrior.load(tmp_path / "shipped.pt").denoiser.config == prior.denoiser.config
    state["denoiser_config"][key] = value
    atomic_torch_save(state, tmp_path / "old.pt")
    with pytest.raises(ValueError, match=rf"old\.pt: made by an earlier design of the denoiser \({key}=") as err:
        ScenePrior.load(tmp_path / "old.pt")
    assert "no longer runs" in str(err.value) and "\n" not in str(err.value)
    assert DenoiserConfig.from_preset("tiny", **RETIRED_FIELDS) == DenoiserConfig.tiny()
    with pytest.raises(ValueError, match=f"earlier design of the denoiser \\({key}="):
        DenoiserConfig.from_preset("small", **{key: value})


@pytest.mark.parametrize("room, anchor", [("bedroom", "bed"), ("livingroom", "sofa"), ("diningroom", "dining_table")])
def test_shipped_prior_loads_and_samples_valid_scenes(room, anchor):
    path = ScenePrior.default_path(room)
    if not path.exists():
        pytest.skip(f"no shipped prior at {path}")
    assert path.stat().st_size < 10_000_000
    prior = ScenePrior.load_default(room)
    config = prior.denoiser.config  # the small preset, with or without slot identity
    assert prior.spec.name == room and config == DenoiserConfig.from_preset("small", slot_embedding=config.slot_embedding)
    floors = _floors() * 3
    batch = prior.sample(floors, num_steps=20, generator=torch.Generator().manual_seed(0))
    counts = batch.mask.sum(1)
    assert (counts >= 1).all() and (counts <= prior.num_slots).all()
    # a trained prior puts objects inside the room's bounds and makes the room's main furniture
    labels = [prior.spec.vocabulary[i] for i in batch.labels[batch.mask].tolist()]
    assert any(anchor in lbl for lbl in labels)
    inside = []
    for i, floor in enumerate(batch.floors):
        xmin, zmin, xmax, zmax = floor.bounds
        t = batch.translations[i][batch.mask[i]]
        inside.append((t[:, 0] > xmin - 0.3) & (t[:, 0] < xmax + 0.3) & (t[:, 2] > zmin - 0.3) & (t[:, 2] < zmax + 0.3))
    assert torch.cat(inside).float().mean() > 0.8  # object centres near or inside the floor's bounding box


@pytest.mark.parametrize("room", ["bedroom", "livingroom", "diningroom"])
def test_environment_default_stats_are_the_shipped_priors(room):
    from pathlib import Path

    import iarcs_env

    path = Path(iarcs_env.__file__).parent / "data" / "stats" / f"{room}.json"
    if not ScenePrior.default_path(room).exists() or not path.exists():
        pytest.skip(f"no shipped {room} prior or environment statistics")
    prior, stats = ScenePrior.load_default(room), DatasetStats.load(path)
    assert stats.bounds_translations == pytest.approx(prior.stats.bounds_translations)
    assert stats.bounds_sizes == pytest.approx(prior.stats.bounds_sizes)
    assert stats.class_presence == pytest.approx(prior.stats.class_presence)
    assert stats.translation_frame == prior.stats.translation_frame
    assert stats.class_sizes and stats.class_sizes == prior.stats.class_sizes


def test_the_pointnet_max_pool_matches_the_plain_layers(monkeypatch):
    """:class:`PointMaxPool` (no (B, P, F) activation, a sparse backward) gives the plain layers' features and
    gradients, in float64 to rounding, across chunks, for an all-zero (unconditional) floor whose points tie, and
    for a subset that repeats points."""
    from agents.denoiser import point_subset
    from agents.pointnet import PointMaxPool, PointNetEncoder

    monkeypatch.setattr(PointMaxPool, "CHUNK_ELEMENTS", 2 * 40 * 64)  # two rooms a chunk
    torch.manual_seed(0)
    enc = PointNetEncoder((4, 16, 16, 64, 8)).double()
    points = torch.randn(9, 40, 4, dtype=torch.float64)
    points[3] = 0.0
    for subset in (point_subset(40, 8), point_subset(6, 8)):
        g_global, g_points = torch.randn(9, 8, dtype=torch.float64), torch.randn(9, 8, 64, dtype=torch.float64)
        results = []
        for encode in (PointNetEncoder.encode_reference, PointNetEncoder.encode):
            enc.zero_grad()
            pts = points.clone().requires_grad_(True)
            glob, per_point = encode(enc, pts, subset)
            ((glob * g_global).sum() + (per_point * g_points).sum()).backward()
            results.append([glob.detach(), per_point.detach(), pts.grad] + [p.grad.clone() for p in enc.parameters()])
        for a, b in zip(*results):
            assert torch.allclose(a, b, atol=1e-12)
    assert PointMaxPool.rows_per_chunk(points, enc.point_mlp[-2].weight) == 2
