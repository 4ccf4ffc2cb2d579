"""Relations through the training pipeline, and the design options the relation-learning experiment
(research/relation_learning.py) compares: procedural bedrooms keep every relation, exactly, through encoding,
augmentation and decoding (issue 37); slot embedding, canonical slot order, min-SNR weighting, x0 / v prediction
and given classes each do what they say."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from agents.denoiser import DenoiserConfig, SceneDenoiser, ScenePrior
from agents.pretrain import PretrainConfig, batch_loss, draw_batch
from agents.pretrain_data import SceneTensors, encode_batch, stats_for_training
from iarcs_env import relation_fidelity as rf
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.rooms import get_room
from iarcs_env.scene import SceneBatch
from iarcs_env.schedule import PREDICTION_TYPES, NoiseSchedule
from scene_factory import box, make_layout

BEDROOM = get_room("bedroom")


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def rooms():
    return generate_layouts("bedroom", 160, seed=3)


# --------------------------------------------------------------------------------------------------------
# the data keeps its relations through the training pipeline (catches data bugs)
# --------------------------------------------------------------------------------------------------------
def _turns(original: torch.Tensor, turned: torch.Tensor) -> list[int]:
    """The quarter turns about +y that took each room's floor points (S, P, 4) to ``turned``."""
    out = []
    for a, b in zip(original[..., :2], turned[..., :2]):
        c = [round(math.cos(k * math.pi / 2)) for k in range(4)]
        s = [round(math.sin(k * math.pi / 2)) for k in range(4)]
        ks = [k for k in range(4) if torch.allclose(torch.stack([c[k] * a[:, 0] + s[k] * a[:, 1],
                                                                 -s[k] * a[:, 0] + c[k] * a[:, 1]], -1), b, atol=1e-5)]
        assert len(ks) == 1
        out.append(ks[0])
    return out


@pytest.mark.parametrize("design", ["present", "slot_identity", "dataset_frame"])
def test_the_relations_survive_encoding_augmentation_and_decoding_exactly(rooms, design):
    """Procedural bedrooms as training draws them (90-degree rotations; shuffled slots, or for slot identity the
    canonical order) and encodes them, decoded as the prior decodes samples (on the floors rotated alike): every
    room's objects, every relation rate and every relation, room by room, are the data's."""
    canonical = design == "slot_identity"
    stats = replace(stats_for_training(rooms, "bedroom", True),
                    translation_frame="dataset" if design == "dataset_frame" else "room")
    data = SceneTensors.from_layouts(rooms, BEDROOM.max_objects, canonical_order=canonical)
    batch = data.batch(torch.arange(len(rooms)), torch.Generator().manual_seed(0), rotate=True, permute=not canonical)
    x0, _ = encode_batch(BEDROOM, stats, *batch)
    turns = _turns(data.floor_points, batch[4])
    assert set(turns) == {0, 1, 2, 3}
    floors = [lay.centred().floor.rotated(k * math.pi / 2) for lay, k in zip(rooms, turns)]
    decoded = SceneBatch.decode(x0, stats, floors)
    plain = SceneBatch.from_layouts(rooms, num_slots=BEDROOM.max_objects).labels
    if canonical:
        assert torch.equal(decoded.labels, plain.sort(1).values)  # sorted by class, empty slots last
    else:
        assert not torch.equal(decoded.labels, plain)  # the slots were shuffled
    assert torch.equal(decoded.labels.sort(1).values, plain.sort(1).values)  # every room's objects, class by class
    rates = rf.relation_rates(rooms)
    assert all(r["holds"] > 0 for r in rates.values())  # every relation is in the data, to be kept or lost
    assert rf.relation_rates(decoded) == rates
    before, after = rf.relation_flags(rooms), rf.relation_flags(decoded)
    for name in before:
        assert np.array_equal(before[name][0], after[name][0]) and np.array_equal(before[name][1], after[name][1])


# --------------------------------------------------------------------------------------------------------
# the design options
# --------------------------------------------------------------------------------------------------------
def test_canonical_order_sorts_by_class_with_empty_slots_last(rooms):
    objects = [box("wardrobe", 4.0, 0.4, 0.8, 0.3), box("nightstand", 1.4, 0.25, 0.25, 0.2),
               box("double_bed", 2.5, 1.0, 0.8, 1.0), box("nightstand", 3.6, 0.25, 0.25, 0.2)]
    lay = make_layout(objects, floor=[(0, 0), (5, 0), (5, 5), (0, 5)])
    data = SceneTensors.from_layouts([lay], BEDROOM.max_objects, canonical_order=True)
    names = [BEDROOM.vocabulary[i] for i in data.labels[0]]
    assert names == ["double_bed", "nightstand", "nightstand", "wardrobe"] + ["empty"] * 8
    plain = SceneTensors.from_layouts([lay], BEDROOM.max_objects)
    for i, j in enumerate([2, 1, 3, 0]):  # the geometry moves with its object; a stable sort keeps the nightstands'
        assert torch.equal(data.translations[0, i], plain.translations[0, j])
        assert torch.equal(data.half_sizes[0, i], plain.half_sizes[0, j]) and data.yaws[0, i] == plain.yaws[0, j]
    with pytest.raises(ValueError, match="permutation_augment"):
        PretrainConfig(canonical_order=True)
    # what training draws from (pretrain.train's data)
    from agents.pretrain_data import training_data
    cfg = PretrainConfig(canonical_order=True, permutation_augment=False, val_scenes=16)
    train, val, _ = training_data(cfg, rooms, log=lambda *a: None, progress=False)
    for part in (train, val):
        assert torch.equal(part.labels, part.labels.sort(1).values) and len(part)


def test_slot_embedding_makes_the_network_not_permutation_equivariant():
    x, t, floor = torch.randn(2, 12, BEDROOM.feature_dim), torch.tensor([5, 600]), torch.randn(2, 256, 4)
    perm = torch.randperm(12, generator=torch.Generator().manual_seed(1))
    for slots in (False, True):
        torch.manual_seed(0)
        net = SceneDenoiser(DenoiserConfig.from_preset("tiny", slot_embedding=slots), BEDROOM.feature_dim).eval()
        with torch.no_grad():
            for p in net.parameters():
                p.copy_(torch.randn(p.shape) * 0.2)
            out = net(x, t, floor)
            assert torch.allclose(net(x[:, perm], t, floor), out[:, perm], atol=1e-5) != slots
    assert DenoiserConfig().slot_embedding is False  # the shipped design: exchangeable slots


def test_min_snr_weights():
    schedule = NoiseSchedule()
    t = torch.arange(1000)
    abar = schedule.alphas_cumprod.double()
    snr = abar / (1 - abar)
    w = schedule.min_snr_weights(t)
    assert torch.allclose(w.double(), snr.clamp(max=5) / snr, rtol=1e-5)
    assert w[snr < 5].eq(1).all() and w[0] < 1e-3 and (w.diff() >= -1e-6).all()  # low-noise steps weigh less
    x0 = NoiseSchedule(prediction_type="sample").min_snr_weights(t).double()
    v = NoiseSchedule(prediction_type="v_prediction").min_snr_weights(t).double()
    assert torch.allclose(x0, snr.clamp(max=5), rtol=1e-5)
    assert torch.allclose(v, snr.clamp(max=5) / (snr + 1), rtol=1e-5)
    # pretraining: each scene's loss times its weight
    rooms = generate_layouts("bedroom", 16, seed=3)
    stats = replace(stats_for_training(rooms, "bedroom", True), translation_frame="room")
    cfg = PretrainConfig(preset="tiny", loss_weighting="min_snr")
    batch = draw_batch(SceneTensors.from_layouts(rooms, 12), cfg, BEDROOM, stats, torch.Generator().manual_seed(0), 16)
    torch.manual_seed(0)
    net = SceneDenoiser(cfg.denoiser_config(), BEDROOM.feature_dim)
    plain = batch_loss(net, schedule, batch, replace(cfg, loss_weighting="none"), BEDROOM, stats, None)
    weighted = batch_loss(net, schedule, batch, cfg, BEDROOM, stats, None)
    assert torch.allclose(weighted, plain * schedule.min_snr_weights(batch.t))


@pytest.mark.parametrize("kind", PREDICTION_TYPES)
def test_prediction_types_train_and_sample_consistently(kind):
    """An exact prediction of each kind: zero loss, the true x0 and noise back, and the same DDIM step."""
    schedule = NoiseSchedule(prediction_type=kind)
    g = torch.Generator().manual_seed(0)
    x0, noise = torch.rand(4, 12, 30, generator=g) * 2 - 1, torch.randn(4, 12, 30, generator=g)
    t = torch.tensor([0, 10, 500, 999])
    x_t = schedule.q_sample(x0, t, noise)
    exact = schedule.training_target(x0, noise, t)
    assert float(schedule.training_loss(lambda x, tt: exact, x0, t=t, noise=noise)) < 1e-10
    assert torch.allclose(schedule.predict_x0(x_t, t, exact), x0, atol=1e-3)
    assert torch.allclose(schedule.predict_eps(x_t[1:], t[1:], exact[1:]), noise[1:], atol=1e-3)
    schedule.set_timesteps(20)
    eps_schedule = NoiseSchedule()
    eps_schedule.set_timesteps(20)
    t = torch.full((4,), 500)
    x_t = schedule.q_sample(x0, t, noise)
    ours = schedule.step(schedule.training_target(x0, noise, t), t, x_t, eta=0.0)
    theirs = eps_schedule.step(noise, t, x_t, eta=0.0)
    assert torch.allclose(ours.mean, theirs.mean, atol=1e-5)


def test_classes_given_conditions_on_clean_classes_and_learns_geometry_only():
    rooms = generate_layouts("bedroom", 16, seed=3)
    stats = replace(stats_for_training(rooms, "bedroom", True), translation_frame="room")
    cfg = PretrainConfig(preset="tiny", classes_given=True)
    batch = draw_batch(SceneTensors.from_layouts(rooms, 12), cfg, BEDROOM, stats, torch.Generator().manual_seed(0), 16)
    seen = []

    def model(x, t, floor, classes=0.0):
        seen.append(x)
        out = torch.zeros_like(x)
        out[..., 8:] = classes
        return out

    from agents.pretrain import loss_feature_weights
    weights = loss_feature_weights(cfg, BEDROOM.feature_dim)
    loss = batch_loss(model, NoiseSchedule(), batch, cfg, BEDROOM, stats, weights)
    assert torch.equal(seen[0][..., 8:], batch.x0[..., 8:])  # the clean one-hot at every t
    assert not torch.equal(seen[0][..., :8], batch.x0[..., :8])  # noisy geometry
    assert torch.allclose(loss, batch.noise[..., :8].square().flatten(1).mean(1))  # the mean over the geometry
    other = batch_loss(lambda x, t, f: model(x, t, f, classes=3.0), NoiseSchedule(), batch, cfg, BEDROOM, stats,
                       weights)
    assert torch.equal(loss, other)  # the class outputs do not count
    # sampling with given classes returns those classes
    prior = ScenePrior.create("bedroom", stats, "tiny")
    labels = SceneTensors.from_layouts(rooms[:4], 12).labels
    scenes = prior.sample([lay.floor for lay in rooms[:4]], num_steps=2, classes=labels,
                          generator=torch.Generator().manual_seed(0))
    assert torch.equal(scenes.labels, labels)
