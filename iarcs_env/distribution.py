"""Distribution metrics between generated and real scenes: FID, KID and SCA on top-down renders.

Renders: :func:`iarcs_env.render.render_layout` of each layout, class-coloured, with a FIXED view
per room type (:data:`RENDER_EXTENT`, the half width in metres of the square view: ATISS's 3.1 m for
bedrooms, 6.2 m for living and dining rooms), so that one pixel is the same size in every image; larger
rooms are cropped. Default resolution 64 x 64 px (CPU friendly; ``size`` changes it).

Features (``features=``):

* ``"cnn"`` (default): a small CNN that this project trains itself on the reference renders (CLIP and
  Inception weights cannot be downloaded here). Targets: which classes are present (multi-label), the
  object count, and an 8 x 8 furniture-occupancy map of the image, so that the features encode content
  and layout; a few epochs with flips and quarter turns as augmentation. The 128-d penultimate layer is
  the feature. The trained weights are cached by a hash of the reference renders and the settings in
  ``$IARCS_CACHE_DIR`` (default ``~/.cache/iarcs/render_cnn``) — outside the repository, as weights
  trained on research-only data must never be committed.
* ``"clip:PATH"``: CLIP image embeddings from a local checkpoint folder loadable by
  ``transformers.CLIPModel.from_pretrained(PATH)`` (renders at 224 px).

Every result names the extractor used (``feature_extractor``).

Both feature sets are first z-scored with the reference set's per-dimension mean and deviation and each
vector scaled to norm sqrt(d) (:func:`standardise`), so the numbers do not depend on a network's units.

* FID: Fréchet distance between Gaussians fitted to the two feature sets.
* KID: unbiased squared MMD with the cubic polynomial kernel ``(x.y / d + 1)^3``, averaged over random
  subsets (as in clean-fid); reported as is (papers often print KID x 1000).
* SCA: scene classification accuracy — a small CNN trained on renders to tell generated from real
  (equal numbers of each, 80/20 train/test split); the test accuracy is reported. 0.5 is best.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from scipy import linalg
from torch import nn

from .geometry import single_thread
from .render import render_layout
from .rooms import get_room
from .scene import Layout

#: Half width (m) of the square top-down view used for the distribution metrics, per room type.
RENDER_EXTENT = {"bedroom": 3.1, "livingroom": 6.2, "diningroom": 6.2}
DEFAULT_SIZE = 64
_CNN_VERSION = 1


def render_set(layouts: Sequence[Layout], size: int = DEFAULT_SIZE, extent: float | None = None,
               progress: bool = False, desc: str = "render") -> np.ndarray:
    """Top-down renders ``(n, size, size, 3)`` uint8 with the fixed extent of the room type."""
    if not layouts:
        raise ValueError("no scenes to render")
    ext = extent or RENDER_EXTENT[get_room(layouts[0].room_type).name]
    it = layouts
    if progress:
        from tqdm import tqdm

        it = tqdm(layouts, desc=desc, unit="scene", leave=False)
    return np.stack([render_layout(lay, size=size, extent=ext, show_front=True) for lay in it])


@torch.no_grad()
def _recalibrate_batchnorm(model: nn.Module, x: torch.Tensor, batch_size: int = 128) -> None:
    """Exact BatchNorm statistics over ``x`` (cumulative averages in train mode, no gradient). After a
    few hundred steps the running averages are still far from the data, and eval mode would be wrong."""
    bns = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    for bn in bns:
        bn.reset_running_stats()
        bn.momentum = None
    model.train()
    for start in range(0, len(x), batch_size):
        model(x[start:start + batch_size])
    model.eval()


def _to_tensor(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div(255.0)


# ------------------------------------------------------------------------------------------------------
# the project's own render CNN
# ------------------------------------------------------------------------------------------------------
class RenderCNN(nn.Module):
    """Four stride-2 convolutions and a 128-d feature layer; heads for the training targets."""

    def __init__(self, num_classes: int, size: int = DEFAULT_SIZE, feature_dim: int = 128, occupancy: int = 8):
        super().__init__()
        chans = [3, 32, 64, 128, 128]
        layers = []
        for a, b in zip(chans[:-1], chans[1:]):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1), nn.BatchNorm2d(b), nn.ReLU(inplace=True)]
        self.conv = nn.Sequential(*layers)
        side = max(size // 16, 1)
        self.feature = nn.Linear(128 * side * side, feature_dim)
        self.occupancy = occupancy
        self.heads = nn.Linear(feature_dim, num_classes + 1 + occupancy * occupancy)
        self.num_classes = num_classes

    def features(self, x: torch.Tensor) -> torch.Tensor:
        return self.feature(self.conv(x).flatten(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.heads(torch.relu(self.features(x)))


def _targets(layouts: Sequence[Layout], images: np.ndarray, occupancy: int = 8) -> np.ndarray:
    spec = get_room(layouts[0].room_type)
    presence = np.zeros((len(layouts), len(spec.classes)), dtype=np.float32)
    for i, lay in enumerate(layouts):
        for lbl in lay.labels:
            presence[i, spec.class_index(lbl)] = 1.0
    count = np.array([[len(lay) / spec.max_objects] for lay in layouts], dtype=np.float32)
    # furniture pixels: neither background (white) nor bare floor (light grey)
    img = images.astype(np.int16)
    furniture = ~((np.abs(img - 255).max(-1) < 3) | (np.abs(img - 222).max(-1) < 3))
    n, h, w = furniture.shape
    cell = h // occupancy
    occ = furniture[:, : cell * occupancy, : cell * occupancy].reshape(n, occupancy, cell, occupancy, cell).mean((2, 4))
    return np.concatenate([presence, count, occ.reshape(n, -1).astype(np.float32)], 1)


def _augment(x: torch.Tensor, y_occ: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Random quarter turn and flip of the images and of their occupancy maps alike."""
    k = int(torch.randint(0, 4, (1,), generator=g))
    flip = bool(torch.randint(0, 2, (1,), generator=g))
    x, y_occ = torch.rot90(x, k, (2, 3)), torch.rot90(y_occ, k, (1, 2))
    if flip:
        x, y_occ = x.flip(3), y_occ.flip(2)
    return x, y_occ


@single_thread()
def train_render_cnn(layouts: Sequence[Layout], images: np.ndarray, epochs: int = 8, batch_size: int = 64,
                     lr: float = 2e-3, seed: int = 0, progress: bool = False) -> RenderCNN:
    """Train :class:`RenderCNN` on reference renders (class presence, object count, occupancy map)."""
    spec = get_room(layouts[0].room_type)
    size = images.shape[1]
    model = RenderCNN(len(spec.classes), size)
    x = _to_tensor(images)
    y = torch.from_numpy(_targets(layouts, images, model.occupancy))
    K = len(spec.classes)
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    bce = nn.BCEWithLogitsLoss()
    it = range(epochs)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="train feature CNN", unit="epoch", leave=False)
    model.train()
    o = model.occupancy
    for _ in it:
        perm = torch.randperm(len(x), generator=g)
        for start in range(0, len(x), batch_size):
            idx = perm[start:start + batch_size]
            if len(idx) < 2:
                continue
            xb, yb = x[idx], y[idx]
            occ = yb[:, K + 1:].reshape(-1, o, o)
            xb, occ = _augment(xb, occ, g)
            out = model(xb)
            loss = (bce(out[:, :K], yb[:, :K]) + nn.functional.mse_loss(out[:, K], yb[:, K]) * 10
                    + nn.functional.mse_loss(torch.sigmoid(out[:, K + 1:]), occ.reshape(len(idx), -1)) * 10)
            opt.zero_grad()
            loss.backward()
            opt.step()
    _recalibrate_batchnorm(model, x)
    return model


def cache_dir() -> Path:
    return Path(os.environ.get("IARCS_CACHE_DIR", Path.home() / ".cache" / "iarcs")) / "render_cnn"


@dataclass
class FeatureExtractor:
    """Maps renders ``(n, H, W, 3)`` uint8 to features ``(n, d)``; ``name`` says what it is."""

    name: str
    model: nn.Module
    kind: str = "cnn"
    processor: object = None
    size: int = DEFAULT_SIZE

    @torch.no_grad()
    def __call__(self, images: np.ndarray, batch_size: int = 128) -> np.ndarray:
        out = []
        for start in range(0, len(images), batch_size):
            chunk = images[start:start + batch_size]
            if self.kind == "clip":
                inputs = self.processor(images=list(chunk), return_tensors="pt")
                f = self.model.get_image_features(**inputs)
                if not isinstance(f, torch.Tensor):  # newer transformers return an output object
                    f = getattr(f, "image_embeds", None) or f.pooler_output
                f = f / f.norm(dim=-1, keepdim=True)
            else:
                with single_thread():
                    f = self.model.features(_to_tensor(chunk))
            out.append(f.float().cpu().numpy())
        return np.concatenate(out).astype(np.float64)


def render_cnn_extractor(reference: Sequence[Layout], images: np.ndarray | None = None, size: int = DEFAULT_SIZE,
                         epochs: int = 8, seed: int = 0, cache: bool = True, progress: bool = False) -> FeatureExtractor:
    """The project's render CNN trained on ``reference`` (loaded from the cache when already trained)."""
    if images is None:
        images = render_set(reference, size, progress=progress, desc="render reference")
    h = hashlib.sha1(images.tobytes())
    h.update(f"v{_CNN_VERSION}:{size}:{epochs}:{seed}:{get_room(reference[0].room_type).name}".encode())
    digest = h.hexdigest()[:16]
    name = f"render-cnn:{digest} (project CNN trained on {len(images)} reference renders, {size}px, {epochs} epochs)"
    path = cache_dir() / f"{digest}.pt"
    spec = get_room(reference[0].room_type)
    if cache and path.exists():
        model = RenderCNN(len(spec.classes), size)
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        model.eval()
        return FeatureExtractor(name, model, "cnn", size=size)
    model = train_render_cnn(reference, images, epochs=epochs, seed=seed, progress=progress)
    if cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.save(model.state_dict(), path)
        except OSError:
            pass  # a read-only home: train again next time
    return FeatureExtractor(name, model, "cnn", size=size)


def clip_extractor(path: str | Path) -> FeatureExtractor:
    """CLIP image features from a local checkpoint folder (``transformers`` format)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no CLIP checkpoint at {path} (give a local folder with a transformers CLIP model)")
    try:
        from transformers import CLIPImageProcessor, CLIPModel

        model = CLIPModel.from_pretrained(str(path), local_files_only=True).eval()
        processor = CLIPImageProcessor.from_pretrained(str(path), local_files_only=True)
    except Exception as err:  # noqa: BLE001 - any loading failure becomes one clear message
        raise ValueError(f"could not load a CLIP model from {path}: {type(err).__name__}: {err}") from None
    return FeatureExtractor(f"clip:{path.name}", model, "clip", processor, size=224)


def get_extractor(spec: str, reference: Sequence[Layout], size: int = DEFAULT_SIZE, progress: bool = False,
                  **kwargs) -> FeatureExtractor:
    """``"cnn"`` or ``"clip:PATH"``."""
    if spec == "cnn":
        return render_cnn_extractor(reference, size=size, progress=progress, **kwargs)
    if spec.startswith("clip:"):
        return clip_extractor(spec[5:])
    raise ValueError(f"unknown feature extractor {spec!r}: use 'cnn' or 'clip:PATH'")


# ------------------------------------------------------------------------------------------------------
# FID, KID, SCA
# ------------------------------------------------------------------------------------------------------
def standardise(features: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Z-score both feature sets with the reference set's per-dimension mean and deviation, then scale
    each vector to norm sqrt(d): FID and KID then do not depend on the arbitrary scale of a feature
    network's units, and a few outlier scenes cannot dominate the cubic KID kernel."""
    mu, sd = reference.mean(0), reference.std(0) + 1e-6

    def unit(f):
        z = (f - mu) / sd
        return z * np.sqrt(z.shape[1]) / np.maximum(np.linalg.norm(z, axis=1, keepdims=True), 1e-12)

    return unit(features), unit(reference)


def fid(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussian fits of feature sets ``a (n, d)`` and ``b (m, d)``."""
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = linalg.sqrtm(s1 @ s2)  # (no ``disp``: scipy 1.18 removed it)
    if not np.isfinite(covmean).all():
        eps = np.eye(len(s1)) * 1e-6
        covmean = linalg.sqrtm((s1 + eps) @ (s2 + eps))
    covmean = np.real(covmean)
    value = float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))
    return max(value, 0.0)


def kid(a: np.ndarray, b: np.ndarray, subsets: int = 100, subset_size: int = 1000, seed: int = 0) -> float:
    """Kernel inception distance: unbiased MMD^2 with kernel ``(x.y / d + 1)^3``, mean over subsets."""
    rng = np.random.default_rng(seed)
    d = a.shape[1]
    m = min(len(a), len(b), subset_size)
    if m < 2:
        raise ValueError("KID needs at least 2 scenes in each set")
    vals = []
    ta, tb = torch.from_numpy(np.asarray(a, dtype=np.float64)), torch.from_numpy(np.asarray(b, dtype=np.float64))
    with single_thread():
        for _ in range(subsets):
            x = ta[torch.from_numpy(rng.choice(len(a), m, replace=False))]
            y = tb[torch.from_numpy(rng.choice(len(b), m, replace=False))]
            kxx = (x @ x.T / d + 1) ** 3
            kyy = (y @ y.T / d + 1) ** 3
            kxy = (x @ y.T / d + 1) ** 3
            vals.append(float((kxx.sum() - kxx.trace()) / (m * (m - 1)) + (kyy.sum() - kyy.trace()) / (m * (m - 1))
                              - 2 * kxy.mean()))
    return float(np.mean(vals))


class _SCANet(nn.Module):
    def __init__(self):
        super().__init__()
        chans = [3, 16, 32, 64, 64]
        layers = []
        for a, b in zip(chans[:-1], chans[1:]):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1), nn.BatchNorm2d(b), nn.ReLU(inplace=True)]
        self.conv = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(64, 1))

    def forward(self, x):
        return self.conv(x).squeeze(1)


@single_thread()
def sca(generated: np.ndarray, real: np.ndarray, epochs: int = 10, batch_size: int = 64, lr: float = 2e-3,
        test_fraction: float = 0.2, seed: int = 0) -> float:
    """Scene classification accuracy: test accuracy of a small CNN trained to tell the two image sets
    apart (equal numbers of each, random split). 0.5 means indistinguishable."""
    rng = np.random.default_rng(seed)
    n = min(len(generated), len(real))
    if n < 5:
        raise ValueError("SCA needs at least 5 scenes in each set")
    gi, ri = rng.permutation(len(generated))[:n], rng.permutation(len(real))[:n]
    n_test = max(1, int(round(n * test_fraction)))
    x = np.concatenate([generated[gi], real[ri]])
    y = np.concatenate([np.ones(n), np.zeros(n)]).astype(np.float32)
    test = np.concatenate([np.arange(n_test), n + np.arange(n_test)])
    train = np.setdiff1d(np.arange(2 * n), test)
    xt, yt = _to_tensor(x), torch.from_numpy(y)
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    model = _SCANet()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    loss_fn = nn.BCEWithLogitsLoss()
    tr = torch.from_numpy(train)
    model.train()
    for _ in range(epochs):
        perm = tr[torch.randperm(len(tr), generator=g)]
        for start in range(0, len(perm), batch_size):
            idx = perm[start:start + batch_size]
            if len(idx) < 2:
                continue
            xb = torch.rot90(xt[idx], int(torch.randint(0, 4, (1,), generator=g)), (2, 3))
            if bool(torch.randint(0, 2, (1,), generator=g)):
                xb = xb.flip(3)
            loss = loss_fn(model(xb), yt[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    _recalibrate_batchnorm(model, xt[tr])
    with torch.no_grad():
        pred = model(xt[torch.from_numpy(test)]) > 0
    return float((pred.float() == yt[torch.from_numpy(test)]).float().mean())


def distribution_metrics(generated: Sequence[Layout], reference: Sequence[Layout], features: str = "cnn",
                         size: int = DEFAULT_SIZE, sca_epochs: int = 10, cnn_epochs: int = 8, seed: int = 0,
                         progress: bool = False, extractor: FeatureExtractor | None = None) -> dict:
    """FID, KID and SCA between ``generated`` and ``reference`` layouts; names the extractor used."""
    generated, reference = list(generated), list(reference)
    if not generated or not reference:
        raise ValueError("distribution metrics need generated and reference scenes")
    img_gen = render_set(generated, size, progress=progress, desc="render generated")
    img_ref = render_set(reference, size, progress=progress, desc="render reference")
    if extractor is None:
        if features == "cnn":
            extractor = render_cnn_extractor(reference, img_ref, size=size, epochs=cnn_epochs, seed=seed,
                                             progress=progress)
        else:
            extractor = get_extractor(features, reference, size=size)
    if extractor.kind == "clip":
        big_gen = render_set(generated, extractor.size, progress=progress, desc="render generated (CLIP)")
        big_ref = render_set(reference, extractor.size, progress=progress, desc="render reference (CLIP)")
        f_gen, f_ref = extractor(big_gen), extractor(big_ref)
    else:
        f_gen, f_ref = extractor(img_gen), extractor(img_ref)
    f_gen, f_ref = standardise(f_gen, f_ref)
    return {
        "FID": fid(f_gen, f_ref),
        "KID": kid(f_gen, f_ref, seed=seed),
        "SCA": sca(img_gen, img_ref, epochs=sca_epochs, seed=seed),
        "feature_extractor": extractor.name,
        "render_size": size,
        "render_extent": RENDER_EXTENT[get_room(reference[0].room_type).name],
    }
