"""Backbone weights: loading, saving and the shipped in-domain default.

Weights are safetensors files (no pickle: a weights file cannot run code) with timm's
``resnet10t`` parameter names, so two sources load the same way:

* ImageNet: ``model.safetensors`` of ``timm/resnet10t.c3_in1k`` on the Hugging Face Hub
  (its classifier ``fc.*`` is ignored) - the paper's ImageNet-pretrained ResNet-10;
* in-domain: :data:`DEFAULT_WEIGHTS`, written by ``bench encoder train``
  (:mod:`window_bench.pixels.pretrain`), float16, with its training record in the file's
  metadata (``window_bench.*`` keys).

A wrong file fails with one line naming it and what is wrong (not a safetensors file,
missing keys, unexpected keys, wrong shapes). There is no silent random backbone:
:func:`resolve_backbone` refuses to build one unless asked by ``allow_random=True``.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from window_bench.pixels.encoder import ResNet10, frozen

#: The shipped in-domain encoder (``bench encoder train`` writes it; see docs/pixels.md).
DEFAULT_WEIGHTS = Path(__file__).with_name("assets") / "resnet10_window.safetensors"
FORMAT = "window-bench resnet10t backbone"
_IGNORED_PREFIXES = ("fc.",)          # timm's ImageNet classifier
_OPTIONAL_SUFFIX = ".num_batches_tracked"


class WeightsError(ValueError):
    """A weights file that is not a ResNet-10 (timm ``resnet10t``) backbone."""


def _expected() -> dict[str, torch.Size]:
    return {k: v.shape for k, v in ResNet10().state_dict().items()}


def read_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The backbone tensors (float32, timm names) and the metadata of a safetensors file;
    raises :class:`WeightsError` for a file that does not hold a complete backbone."""
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"encoder weights {str(path)!r}: no such file")
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = dict(f.metadata() or {})
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise WeightsError(f"encoder weights {str(path)!r} is not a safetensors weights "
                           f"file ({str(e).splitlines()[0][:120]})") from None
    tensors = {k: v for k, v in tensors.items() if not k.startswith(_IGNORED_PREFIXES)}
    expected = _expected()
    missing = [k for k in expected if k not in tensors and not k.endswith(_OPTIONAL_SUFFIX)]
    unexpected = [k for k in tensors if k not in expected]
    if missing or unexpected:
        what = []
        if missing:
            what.append(f"{len(missing)} missing keys (e.g. {', '.join(missing[:3])})")
        if unexpected:
            what.append(f"{len(unexpected)} unexpected keys (e.g. {', '.join(unexpected[:3])})")
        raise WeightsError(f"encoder weights {str(path)!r} is not a ResNet-10 (timm "
                           f"resnet10t) state dict: {'; '.join(what)}")
    wrong = [f"{k} {tuple(v.shape)} (expected {tuple(expected[k])})"
             for k, v in tensors.items() if v.shape != expected[k]]
    if wrong:
        raise WeightsError(f"encoder weights {str(path)!r}: {len(wrong)} tensors have the "
                           f"wrong shape, e.g. {wrong[0]}")
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise WeightsError(f"encoder weights {str(path)!r}: non-finite values in {bad[0]}")
    out = {k: (v.float() if v.is_floating_point() else v) for k, v in tensors.items()}
    return out, metadata


def load_backbone(path: str | Path) -> ResNet10:
    """A frozen :class:`ResNet10` with the weights of ``path`` (see :func:`read_weights`)."""
    tensors, _ = read_weights(path)
    model = ResNet10()
    model.load_state_dict(tensors, strict=False)   # num_batches_tracked may be absent
    return frozen(model)


def save_backbone(model: ResNet10, path: str | Path, metadata: dict | None = None) -> int:
    """Write ``model``'s weights as float16 safetensors, atomically (temp file + rename);
    ``metadata`` values are stored as JSON strings under ``window_bench.<key>``. Returns
    the file size in bytes."""
    from safetensors.torch import save

    from window_bench.harness.evaluation import atomic_write

    tensors = {k: (v.detach().to(torch.float16) if v.is_floating_point() else v.detach())
               .contiguous() for k, v in model.state_dict().items()}
    meta = {"format": FORMAT}
    meta.update({f"window_bench.{k}": json.dumps(v) for k, v in (metadata or {}).items()})
    atomic_write(path, lambda f: f.write(save(tensors, metadata=meta)))
    return Path(path).stat().st_size


def weights_record(path: str | Path) -> dict:
    """The ``window_bench.*`` metadata of a weights file, decoded (empty for a timm file)."""
    _, meta = read_weights(path)
    prefix = "window_bench."
    return {k[len(prefix):]: json.loads(v) for k, v in meta.items() if k.startswith(prefix)}


def resolve_backbone(weights: str | Path | None = None, *,
                     allow_random: bool = False) -> tuple[ResNet10, str]:
    """The frozen backbone of the pixel track and a label for results files.

    ``weights``: a safetensors file (``--encoder-weights PATH``) or ``None`` for the
    shipped in-domain default. ``allow_random=True`` (``--allow-random-encoder``) is the
    only way to a randomly initialised backbone, for tests and plumbing checks; a missing
    default is otherwise an error, never a silent random encoder."""
    if weights is not None:
        return load_backbone(weights), str(weights)
    if DEFAULT_WEIGHTS.is_file():
        return load_backbone(DEFAULT_WEIGHTS), f"default:{DEFAULT_WEIGHTS.name}"
    if allow_random:
        with torch.random.fork_rng():   # seeded, without touching the caller's RNG
            torch.manual_seed(0)
            return frozen(ResNet10()), "random (allow_random)"
    raise WeightsError(f"no encoder weights: the in-domain default {DEFAULT_WEIGHTS.name} is "
                       f"not in this install; run `bench encoder train`, or pass "
                       f"--encoder-weights PATH (e.g. timm resnet10t model.safetensors)")
