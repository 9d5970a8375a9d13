"""Read-outs of the frozen backbone's maps for probes: which layer, and what of it is kept.

* ``layer``: ``layer4`` is the pixel track's 512 x 4 x 4 map (stride 32); ``layer3``
  (256 x 8 x 8, stride 16) and ``layer2`` (128 x 16 x 16, stride 8) keep finer positions.
* ``readout``: ``maps`` keeps the whole map (flattened, rounded to float16 as the pixel
  track caches it); ``keypoints`` keeps, per channel, the expected image position under a
  softmax over the map (spatial softmax, as in Levine et al.'s deep spatial autoencoders):
  2 values per channel in [-1, 1], x then y, which move continuously with a feature's
  position instead of jumping from cell to cell.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from window_bench.pixels.encoder import ResNet10

LAYERS = ("layer2", "layer3", "layer4")
READOUTS = ("maps", "keypoints")


def check_readout(layer: str, readout: str) -> None:
    """Raise ``ValueError`` naming the bad value and the allowed ones."""
    if layer not in LAYERS:
        raise ValueError(f"layer {layer!r} is not one of {', '.join(LAYERS)}")
    if readout not in READOUTS:
        raise ValueError(f"readout {readout!r} is not one of {', '.join(READOUTS)}")


def backbone_map(backbone: ResNet10, images: torch.Tensor, layer: str = "layer4") -> torch.Tensor:
    """The backbone's output after ``layer`` for ``(B, H, W, 3)`` uint8 images."""
    check_readout(layer, "maps")
    x = (images.permute(0, 3, 1, 2).float() - backbone.mean) / backbone.std
    x = backbone.maxpool(F.relu(backbone.bn1(backbone.conv1(x))))
    for name in ("layer1", *LAYERS[: LAYERS.index(layer) + 1]):
        x = getattr(backbone, name)(x)
    return x


def spatial_softmax(maps: torch.Tensor) -> torch.Tensor:
    """``(B, C, H, W)`` -> ``(B, 2C)``: per channel the softmax-weighted mean x, then y, of
    the cell centres on a [-1, 1] grid."""
    b, c, h, w = maps.shape
    p = torch.softmax(maps.flatten(2), -1).view(b, c, h, w)
    xs = torch.linspace(-1.0, 1.0, w, dtype=maps.dtype)
    ys = torch.linspace(-1.0, 1.0, h, dtype=maps.dtype)
    return torch.cat([(p.sum(2) * xs).sum(2), (p.sum(3) * ys).sum(2)], 1)


@torch.inference_mode()
def readout_features(backbone: ResNet10, images: np.ndarray, layer: str = "layer4",
                     readout: str = "maps", batch: int = 64) -> np.ndarray:
    """``(N, H, W, 3)`` uint8 images of one view -> ``(N, D)`` float32 features."""
    check_readout(layer, readout)
    backbone.eval()
    out = []
    for start in range(0, len(images), batch):
        m = backbone_map(backbone, torch.from_numpy(np.ascontiguousarray(images[start:start + batch])), layer)
        f = m.to(torch.float16).float().flatten(1) if readout == "maps" else spatial_softmax(m)
        out.append(f.numpy())
    return np.concatenate(out).astype(np.float32)
