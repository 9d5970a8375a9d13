"""What the harness runs, under the names that methods, policy files, results and grids use.

The harness (:mod:`window_bench.harness`) defines the registries and never imports a learner
or a track; this module, above it, fills them: the agents of Table 1 and their pixel-track
pairings (:data:`~window_bench.harness.methods.AGENTS`), the observation tracks
(:data:`~window_bench.harness.tracks.TRACKS`) and the published agent configs
(:data:`~window_bench.harness.methods.PRESETS`). ``import window_bench`` imports it, so every
process finds the same entries: ``bench``, the cells of ``bench sweep``, evaluation workers,
tests and scripts. A learner is imported when a run first asks for its kind, and only then
(``bench methods`` loads none).
"""

from __future__ import annotations

from window_bench.harness.methods import register_agent, register_preset
from window_bench.harness.tracks import Track, register_track
from window_bench.pixels.track import PixelTrack, SeatPixelTrack


# ---------------------------------------------------------------------------- agents
def _qcfql():
    from baselines.qcfql import QCFQLAgent

    return QCFQLAgent


def _hilserl():
    from baselines.hilserl import HILSERLAgent

    return HILSERLAgent


def _act():
    from baselines.act import ACTAgent

    return ACTAgent


def _sac():
    from baselines.sac import SACAgent

    return SACAgent


def _qcfql_pixels():
    from window_bench.pixels.agent import PixelQCFQL

    return PixelQCFQL


def _hilserl_pixels():
    from window_bench.pixels.agent import PixelHILSERL

    return PixelHILSERL


def _sac_pixels():
    from window_bench.pixels.sac import PixelSACAgent

    return PixelSACAgent


def _act_pixels():
    from window_bench.pixels.agent import PixelACT

    return PixelACT


register_agent("qcfql", load=_qcfql)
register_agent("hilserl", load=_hilserl)
register_agent("act", load=_act)
register_agent("sac", load=_sac)
register_agent("qcfql-pixels", load=_qcfql_pixels)      # bench run --track pixels
register_agent("hilserl-pixels", load=_hilserl_pixels)
register_agent("sac-pixels", load=_sac_pixels)
register_agent("act-pixels", load=_act_pixels)


# ---------------------------------------------------------------------------- tracks
register_track(Track())         # state: the privileged 52-float observation
register_track(PixelTrack())    # pixels: the paper's two RGB views + proprioception
register_track(SeatPixelTrack())   # pixels-seat: two cameras on the opening's corners


# ---------------------------------------------------------------------------- presets
def _qcfql_as_published() -> dict:
    from baselines.qcfql import PAPER_AGENT   # the overrides that restore the paper's agent

    return PAPER_AGENT


def _hilserl_own() -> dict:
    from baselines.hilserl import HILSERL_OWN   # HIL-SERL's own protocol and settings

    return HILSERL_OWN


register_preset("qcfql-as-published", load=_qcfql_as_published)
register_preset("hilserl-own", load=_hilserl_own)
