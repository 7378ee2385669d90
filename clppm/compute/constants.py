"""Codes the host writes into the kernels' parameters and reads back from their tallies, named
once: kernels/constants.h defines the same names with the same values for the kernels, and
tests/test_constants.py checks the two files against each other.
"""
from __future__ import annotations

from enum import IntEnum

#: light source kinds (Params.src_kind, EyeParams.light_kind), by the config's ``light.kind``
SOURCE = {"pencil": 0, "wide": 1, "point": 2}               # SRC_PENCIL, SRC_WIDE, SRC_POINT

#: photon storage rules (Params.store_rule), by the config's ``render.storage``
STORAGE = {"all": 0, "importance": 1}                       # STORE_RULE_ALL, STORE_RULE_IMPORTANCE


class EyeMode(IntEnum):
    """The eye pass's modes (eye_pass's argument ``write``)."""

    COUNT = 0                # count each ray's sample points and pieces
    STORE = 1                # store them at the counts' prefix sums
    STORE_GEOMETRY = 2       # and each piece's geometry (the beam estimator)


#: the photon pass's tally categories per band, in the kernel's order (TALLY_*); the layers'
#: absorption tallies follow from TALLY_ABSORBED0
TALLIES = ("specular", "diffuse", "transmitted", "lost", "rr_gain", "rr_loss", "missed",
           "diffuse_cone")
TALLY = {name: i for i, name in enumerate(TALLIES)}
TALLY_ABSORBED0 = len(TALLIES)


def c_names() -> dict[str, int]:
    """Every constant by its kernels/constants.h name."""
    return {**{f"SRC_{k.upper()}": v for k, v in SOURCE.items()},
            **{f"STORE_RULE_{k.upper()}": v for k, v in STORAGE.items()},
            **{f"EYE_{m.name}": int(m) for m in EyeMode},
            **{f"TALLY_{k.upper()}": v for k, v in TALLY.items()},
            "TALLY_ABSORBED0": TALLY_ABSORBED0}
