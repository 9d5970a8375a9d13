"""The paper's observation encoder (Appendix, Table 8) in plain torch.

* :class:`ResNet10` - the frozen visual backbone: a ResNet-10 in timm's ``resnet10t`` layout
  (deep tiered 3x3 stem 24-32-64, one BasicBlock per stage at 64/128/256/512 channels,
  average-pool shortcuts, BatchNorm). Its parameter names are timm's, so the ImageNet
  weights ``timm/resnet10t.c3_in1k`` (``model.safetensors``) load as they are. A 128 x 128
  RGB view becomes a 512 x 4 x 4 feature map (stride 32).
* :class:`SpatialLearnedEmbeddings` - HIL-SERL's trainable spatial aggregation: ``F``
  learned H x W kernels per channel, each summing the channel's map into one number.
* :class:`ViewAggregation` - one view's trainable head, as HIL-SERL's pretrained-ResNet
  encoder: spatial embeddings -> linear bottleneck -> LayerNorm -> tanh, here to the
  paper's 32 dims.
* :class:`PixelObsEncoder` - the fusion of both views' 32-dim embeddings with the 18
  proprioceptive values; its input is the flat observation of
  :class:`window_bench.pixels.features.PixelFeatures` (cached backbone features), so the
  backbone never runs in a gradient update.

HIL-SERL's own ResNet-10 (``resnetv1-10``) differs in the stem (one 7 x 7 convolution) and
uses GroupNorm; its weights are a Flax pickle, which this package does not load (no file we
load may run code), so the timm layout is the one supported here.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

VIEWS = ("wrist_rgb", "side_rgb")     # the env's image keys, in feature order
IMAGE_SIZE = 128
CHANNELS = 512
FEATURE_HW = IMAGE_SIZE // 32         # 4: the backbone's stride is 32
VIEW_FEATURES = CHANNELS * FEATURE_HW * FEATURE_HW   # 8,192 values per view
PROPRIO_DIM = 18                      # q (7), q-dot (7), end-effector position (3), vacuum (1)
FEATURE_VALUES = len(VIEWS) * VIEW_FEATURES          # 16,384 feature-map values, float16-exact
OBS_DIM = FEATURE_VALUES + PROPRIO_DIM               # 16,402: the flat pixel observation
EMBED_DIM = 32                        # per view (Appendix)
SPATIAL_FEATURES = 8                  # HIL-SERL's num_spatial_blocks

# ImageNet statistics: the normalisation the timm weights were trained with.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels)


def _conv3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


class BasicBlock(nn.Module):
    """Two 3 x 3 convolutions with a shortcut; a strided block's shortcut average-pools
    before its 1 x 1 convolution (timm's ``avg_down``), so no input pixel is skipped."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1, self.bn1 = _conv3(cin, cout, stride), _bn(cout)
        self.conv2, self.bn2 = _conv3(cout, cout), _bn(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            pool = (nn.AvgPool2d(2, stride, ceil_mode=True, count_include_pad=False)
                    if stride != 1 else nn.Identity())
            self.downsample = nn.Sequential(pool, nn.Conv2d(cin, cout, 1, bias=False), _bn(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        shortcut = x if self.downsample is None else self.downsample(x)
        return F.relu(y + shortcut)


class ResNet10(nn.Module):
    """ResNet-10 (timm ``resnet10t`` layout) without its classifier: uint8 images in,
    feature maps out. :meth:`forward` takes ``(B, H, W, 3)`` uint8 (the env's layout) and
    returns ``(B, 512, H/32, W/32)`` float32."""

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Sequential(
            nn.Conv2d(3, 24, 3, stride=2, padding=1, bias=False), _bn(24), nn.ReLU(),
            _conv3(24, 32), _bn(32), nn.ReLU(),
            _conv3(32, 64))
        self.bn1 = _bn(64)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64, 1))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1) * 255.0,
                             persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1) * 255.0,
                             persistent=False)
        # NHWC uint8 images permuted to NCHW are channels-last in memory already; weights in
        # the same layout make CPU convolutions about 1.5x faster here.
        self.to(memory_format=torch.channels_last)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"images: expected (B, H, W, 3), got {tuple(images.shape)}")
        x = (images.permute(0, 3, 1, 2).float() - self.mean) / self.std
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))


def frozen(module: nn.Module) -> nn.Module:
    """``module`` in eval mode (BatchNorm uses its running statistics) with every parameter
    excluded from autograd: the paper keeps the backbone frozen throughout training."""
    module.eval()
    module.requires_grad_(False)
    return module


class SpatialLearnedEmbeddings(nn.Module):
    """``out[b, c, f] = sum_{h,w} x[b, c, h, w] * kernel[c, h, w, f]`` flattened to
    ``(B, C * F)``: each channel keeps *where* it fired, which global pooling would lose
    (HIL-SERL's ``SpatialLearnedEmbeddings``; LeCun-normal init as its Flax default)."""

    def __init__(self, channels: int, height: int, width: int, num_features: int,
                 generator: torch.Generator | None = None):
        super().__init__()
        fan_in = height * width * channels
        self.kernel = nn.Parameter(
            torch.randn(channels, height, width, num_features, generator=generator)
            / np.sqrt(fan_in))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("bchw,chwf->bcf", x, self.kernel).flatten(1)


class ViewAggregation(nn.Module):
    """One view's 512 x 4 x 4 feature map -> ``EMBED_DIM`` values in (-1, 1)."""

    def __init__(self, generator: torch.Generator | None = None):
        super().__init__()
        self.spatial = SpatialLearnedEmbeddings(CHANNELS, FEATURE_HW, FEATURE_HW,
                                                SPATIAL_FEATURES, generator)
        self.bottleneck = nn.Linear(CHANNELS * SPATIAL_FEATURES, EMBED_DIM)
        if generator is not None:
            bound = 1.0 / np.sqrt(self.bottleneck.in_features)
            with torch.no_grad():
                self.bottleneck.weight.uniform_(-bound, bound, generator=generator)
                self.bottleneck.bias.uniform_(-bound, bound, generator=generator)
        self.norm = nn.LayerNorm(EMBED_DIM)

    def folded_weight(self) -> torch.Tensor:
        """The spatial kernels and the bottleneck as one (32, 8,192) matrix. Nothing
        nonlinear lies between them, so their composition is one linear map: folding the two
        weights (2 M multiply-adds) turns a batched einsum over 512 channels into a single
        GEMM per batch, with the same function and gradients."""
        k = self.spatial.kernel                                   # (C, H, W, F)
        w = self.bottleneck.weight.view(EMBED_DIM, k.shape[0], k.shape[3])   # (J, C, F)
        return torch.einsum("jcf,chwf->jchw", w, k).reshape(EMBED_DIM, -1)

    def forward(self, fmap: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
        """``weight``: a :meth:`folded_weight` computed once for several batches."""
        weight = self.folded_weight() if weight is None else weight
        return torch.tanh(self.norm(F.linear(fmap.flatten(1), weight, self.bottleneck.bias)))

    def unfolded(self, fmap: torch.Tensor) -> torch.Tensor:
        """HIL-SERL's order of operations (spatial embeddings, then the bottleneck); equal to
        :meth:`forward` up to float rounding."""
        return torch.tanh(self.norm(self.bottleneck(self.spatial(fmap))))


def split_observation(obs: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Flat pixel observations ``(B, OBS_DIM)`` -> (one ``(B, 512, 4, 4)`` map per view,
    proprioception ``(B, 18)``)."""
    if obs.ndim != 2 or obs.shape[1] != OBS_DIM:
        raise ValueError(f"pixel observation: expected (B, {OBS_DIM}), got {tuple(obs.shape)}")
    maps = [obs[:, i * VIEW_FEATURES:(i + 1) * VIEW_FEATURES]
            .reshape(-1, CHANNELS, FEATURE_HW, FEATURE_HW) for i in range(len(VIEWS))]
    return maps, obs[:, len(VIEWS) * VIEW_FEATURES:]


class PixelObsEncoder(nn.Module):
    """Trainable part of the observation encoder: per-view aggregation of the cached
    backbone features, concatenated with the normalised proprioception
    (``2 x 32 + 18 = 82`` values, the input of the actor, critic and teacher MLPs); with a
    ``pose_readout``, its 12 pose features after them (94 values).

    ``proprio_mean`` / ``proprio_std`` fix the proprioception's normaliser (the harness
    computes them from the demonstrations); default identity."""

    out_dim = len(VIEWS) * EMBED_DIM + PROPRIO_DIM

    def __init__(self, seed: int = 0, proprio_mean=None, proprio_std=None, pose_readout=None,
                 view_embeddings: bool = True):
        super().__init__()
        #: False: both views' embeddings enter as zeros (a diagnostic, QC-FQL's config).
        self.view_embeddings = view_embeddings
        #: A fixed :class:`~window_bench.pixels.pose_readout.PoseReadout` whose 12 pose
        #: features follow the 82 values (``out_dim`` 94), or None.
        self.pose_readout = pose_readout
        if pose_readout is not None:
            from window_bench.pixels.pose_readout import FEATURES

            self.out_dim = type(self).out_dim + FEATURES
        gen = torch.Generator().manual_seed(int(seed))
        self.views = nn.ModuleList([ViewAggregation(gen) for _ in VIEWS])
        mean = np.zeros(PROPRIO_DIM) if proprio_mean is None else np.asarray(proprio_mean)
        std = np.ones(PROPRIO_DIM) if proprio_std is None else np.asarray(proprio_std)
        if mean.shape != (PROPRIO_DIM,) or std.shape != (PROPRIO_DIM,):
            raise ValueError(f"proprio_mean/std: expected {PROPRIO_DIM} values each, got "
                             f"shapes {mean.shape} and {std.shape}")
        self.register_buffer("proprio_mean", torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("proprio_std",
                             torch.as_tensor(np.maximum(std, 1e-3), dtype=torch.float32))

    def forward(self, obs: torch.Tensor, weights: list | None = None) -> torch.Tensor:
        maps, proprio = split_observation(obs.float())
        return self.fuse(maps, proprio, weights)

    def fuse(self, maps, proprio: torch.Tensor, weights: list | None = None) -> torch.Tensor:
        """The 82 values from the parts of the observation: one float32 ``(B, 8,192)`` (or
        ``(B, 512, 4, 4)``) map per view and the raw ``(B, 18)`` proprioception; ``weights``:
        the views' :meth:`ViewAggregation.folded_weight`, if computed already."""
        weights = weights or [None] * len(self.views)
        embeds = [agg(m, w) if self.view_embeddings else torch.zeros(len(m), EMBED_DIM)
                  for agg, m, w in zip(self.views, maps, weights)]
        x = ((proprio - self.proprio_mean) / self.proprio_std).clamp(-10.0, 10.0)
        if self.pose_readout is None:
            return torch.cat([*embeds, x], dim=-1)
        with torch.no_grad():
            pose = self.pose_readout(torch.cat([*(m.flatten(1) for m in maps), proprio], 1))
        return torch.cat([*embeds, x, pose], dim=-1)

    def encode_pair(self, obs: torch.Tensor,
                    next_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(embed(obs), embed(next_obs))`` for a TD update: one fold of the weights for
        both, the gradient through ``obs`` only (``s'`` is embedded by the current
        aggregation with the gradient stopped, as DrQ-v2 embeds its next observations)."""
        weights = [agg.folded_weight() for agg in self.views]
        emb = self(obs, weights)
        with torch.no_grad():
            return emb, self(next_obs, weights)
