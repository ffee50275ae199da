"""The version of what the environment produces.

:data:`ENV_VERSION` covers the scenes, the renderer, the pixel layout, the episode numbering, the noise
presets and the expert. It is bumped whenever any of them changes, and data made
by another version (demo stores, episode datasets) is refused with a message that
says so, instead of being reused silently.

History:

* 1: CHW frames; ``paper`` noise symmetric (now ``paper_symmetric``).
* 2: HWC frames (TorchRL's pixel convention); ``paper`` noise is the first
  author's ``NoisyAction.py``; the geodesic distance field agrees with the
  collision model (distances and expert labels changed near walls).
* 3: episodes are numbered (agent i of N plays episodes i, i + N, ...; an
  episode's seed depends on the env seed and its number), so a seed now gives
  other episodes than under version 2; houses may be larger (grid size in the
  house seed) and the homing task exists.
"""
from __future__ import annotations

#: Version of scenes, renderer, pixel layout, noise presets and expert together.
ENV_VERSION = 3


def check_env_version(found: object, what: str) -> None:
    """Raise ``ValueError`` naming ``what`` when ``found`` is not :data:`ENV_VERSION`.

    Examples:
        >>> check_env_version(ENV_VERSION, "demo store /tmp/x")
        >>> check_env_version(1, "dataset /tmp/y")
        Traceback (most recent call last):
        ...
        ValueError: dataset /tmp/y was made by env version 1, but this env is version 3 (scenes, renderer, pixel layout, noise presets or expert changed); make it again.
    """
    if found != ENV_VERSION:
        raise ValueError(
            f"{what} was made by env version {found!r}, but this env is version {ENV_VERSION} "
            "(scenes, renderer, pixel layout, noise presets or expert changed); make it again."
        )
