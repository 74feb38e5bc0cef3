"""The reference amplitude of A-normalised shapes across the field, against a known field."""

import numpy as np
import pytest

from latentz.calibration.reference import REFERENCE_NEIGHBOURS, ReferenceField


def _particles(n: int, sigma: float, seed: int = 0):
    """Particles on a 2048 px field whose ln A_ref is a smooth field plus their own scatter."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 2048, (n, 2))

    def field(x, y):
        return np.log(800.0) + 0.2 * np.sin(x / 700.0) * np.cos(y / 900.0)

    return xy, field, np.exp(field(*xy.T) + rng.normal(0, sigma, n))


def test_the_reference_follows_the_field_and_averages_the_particles_out():
    xy, field, ref = _particles(2000, sigma=0.07)
    points = np.random.default_rng(1).uniform(200, 1848, (500, 2))
    reference = ReferenceField(xy, ref)
    ours = np.log(reference(*points.T)) - field(*points.T)
    # one particle's own value would be off by its whole scatter, 0.07
    assert np.sqrt(np.mean(ours**2)) < 0.07 / np.sqrt(REFERENCE_NEIGHBOURS) * 1.5
    # a particle about its neighbours' mean: its own scatter and the mean's error
    expected = 0.07 * np.sqrt(1 + 1 / REFERENCE_NEIGHBOURS)
    assert reference.scatter == pytest.approx(expected, rel=0.1)


def test_the_scatter_covers_emitters_as_bright_as_the_particles():
    """New emitters from the same population: 1σ of ln A about the reference covers ~68 %."""
    xy, field, ref = _particles(400, sigma=0.07)
    rng = np.random.default_rng(2)
    spots = rng.uniform(100, 1948, (4000, 2))
    own = field(*spots.T) + rng.normal(0, 0.07, len(spots))
    reference = ReferenceField(xy, ref)
    error = own - np.log(reference(*spots.T))
    coverage = np.mean(np.abs(error) <= reference.scatter)
    assert 0.64 <= coverage <= 0.72, coverage


def test_held_out_leaves_each_particle_out_and_skips_missing_values():
    xy, _, ref = _particles(40, sigma=0.05)
    ref[3] = np.nan
    held = ReferenceField(xy, ref).held_out()
    assert np.isnan(held[3]) and np.all(np.isfinite(np.delete(held, 3)))
    # particle 0's own value is not in its held-out reference: changing it leaves that alone
    changed = ref.copy()
    changed[0] *= 10
    assert ReferenceField(xy, changed).held_out()[0] == pytest.approx(held[0])


def test_a_lone_particle_is_its_own_reference_with_an_unknown_scatter():
    lone = ReferenceField(np.array([[10.0, 20.0], [30.0, 40.0]]), np.array([500.0, np.nan]))
    assert lone(np.array([0.0, 900.0]), np.array([0.0, 900.0])) == pytest.approx([500.0, 500.0])
    assert np.isnan(lone.scatter) and np.isnan(lone.held_out()).all()
    with pytest.raises(ValueError, match="needs a calibration particle with a reference"):
        ReferenceField(np.zeros((1, 2)), np.array([np.nan]))
