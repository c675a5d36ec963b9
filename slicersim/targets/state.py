"""Target state: argument checks shared by the targets and the pieces of an atomic update.

:meth:`Target.update <slicersim.targets.base.Target.update>` validates the whole new state off to
the side (:class:`_TargetUpdate`) and only then applies it; the host centre follows
:func:`_host_centre` (relative to the target, or to the field centre).
"""
from __future__ import annotations

import os

from slicersim import validation
from slicersim.errors import ParameterError


class _TargetUpdate:
    """A validated, not yet applied :meth:`Target.update`: the new state of every part."""

    new_sim = sim_update = new_host = host_centre = probe = None

    @property
    def spectrograph(self):
        return self.state.spectrograph

    @property
    def telescope(self):
        return self.state.telescope

    @property
    def aperture_radius_insigma(self):
        return self.state.aperture_radius_insigma


def _host_centre(state, redshift, position, spatial_scale):
    """(x, y) [arcsec] of the host centre from the field centre for a target at ``position``
    [cells]: the state's offset (at ``redshift``) from the target, or from the field centre."""
    dx, dy = state.offset_at(redshift)
    if state.relative:
        return (position[0] * spatial_scale + dx, position[1] * spatial_scale + dy)
    return (dx, dy)


def _move_host(host, centre):
    """Place the target's own host copy at ``centre`` [arcsec] (profile offset or cube centre)."""
    if centre is None:
        return
    if hasattr(host, "profile") and hasattr(host.profile, "offset"):
        if tuple(host.profile.offset) != tuple(centre):
            host.profile.offset = centre
    elif hasattr(host, "centre") and tuple(host.centre) != tuple(centre):
        host.centre = centre


def check_redshift(redshift, name="redshift"):
    """None or a number in (0, :data:`~slicersim.validation.MAX_REDSHIFT`] (ParameterError naming
    ``name`` otherwise: strings, lists, NaN, ≤ 0, 1e300)."""
    if redshift is None:
        return None
    return validation.redshift(name, redshift)


def check_config(config):
    """A configuration name / TOML path or a non-empty list of them (ParameterError otherwise)."""
    items = config if isinstance(config, (list, tuple)) else [config]
    if not items or not all(isinstance(c, (str, os.PathLike)) for c in items):
        raise ParameterError(f"config must be 'cbe', 'eol', a TOML path or a list of them, got "
                             f"{validation.short_repr(config)}")
    return config
