"""bench/studies/band_bias.py --group: a path-traced reference over one band group's bands only,
scaled back to the whole spectrum's units, reads what the whole spectrum's reference reads in
those bands (the path tracer takes one band per path, so the cut spectrum gives each band the
same paths as the whole one at a fraction of them).  Flat forearm, 20x20 pixels (four 10x10
squares of skin), the same paths per band in both."""
from __future__ import annotations

import numpy as np

import band_bias as bb
from clppm import config as C
from clppm.analysis.reference import RefSpec, get_reference

PATHS_PER_BAND = 500            # per square and half: the group's mean to about 0.5 %


def _reference(cfg, nb, dev, tmp_path):
    spec = RefSpec(integrator="pt", resolution=(20, 20), block=10, paths=PATHS_PER_BAND * nb)
    return get_reference(cfg, spec, str(tmp_path), dev=dev, log=lambda *a: None)


def test_a_group_reference_reads_the_whole_spectrums(dev, tmp_path):
    """Caught: the cut reference left in its own spectrum's units (x 7-10 per band).  Its bands'
    place in the whole spectrum is checked exactly (one band off moves the group's mean by
    -2.3 % or +1.4 %, within reach of the two references' noise here: 0.3-0.5 %)."""
    cfg = C.override(C.override(C.load("forearm_flat"), "render", "specular", False), "render", "checkpoint_every", 0)
    group = bb.group_config(cfg, "530-575")
    whole = _reference(cfg, len(C.wavelengths(cfg)), dev, tmp_path)
    cut, idx = bb.group_reference(_reference(group, len(C.wavelengths(group)), dev, tmp_path), cfg, group)
    assert np.array_equal(whole.wl[idx], cut.wl)
    a = whole.spectral[..., idx].sum(-1)        # per square, the group's radiance
    b = cut.spectral.sum(-1)
    assert abs(b.mean() / a.mean() - 1) < 0.03, (a, b)
    # each half of the cut reference is scaled alike
    for h in cut.halves_spectral:
        assert abs(h.sum(-1).mean() / a.mean() - 1) < 0.05
