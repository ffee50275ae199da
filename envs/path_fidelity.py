"""Path fidelity: how closely an agent's path follows the demonstrated route.

Success (ending within the success radius of the route's end) says nothing about
*how* the agent got there: a shortcut straight to the end succeeds as well as a
faithful copy of the route. These metrics score the path itself, after Ilharco et
al. 2019, "General Evaluation for Instruction Conditioned Navigation using Dynamic
Time Warping" (arXiv:1907.05446), as R2R, RxR and VLN-CE report them:

* :func:`dtw_distance`: dynamic time warping between the agent's path and the
  reference route, the least total distance (metres) of an order-preserving
  matching of their points; waiting on the spot or moving at another pace costs
  nothing by itself (time warping), leaving the route does;
* :func:`ndtw`: normalised DTW, ``exp(-DTW / (len(reference) * threshold_m))``
  in (0, 1], 1 iff the path matches the reference point by point;
* :func:`sdtw`: success weighted by nDTW (0 on a failed episode);
* :func:`path_length_ratio`: length travelled over the demonstrated length
  (below 1: a shortcut; above 1: a detour or wandering);
* :func:`wall_hits`: forward steps that the collision model cut short;
* :func:`path_fidelity`: nDTW, SDTW and the length ratio of one episode, for the env.

Distances are Euclidean in the horizontal plane (metres, the house frame), as in
VLN-CE (``habitat_extensions/measures.py``), not geodesic: a point cost is cheap to
compute for every pair of points, and two points on either side of a thin wall are
rare in a path that follows a route (they would be matched as if the wall were not
there). The threshold ``threshold_m`` is the follow protocol's success radius
(callers pass :data:`envs.follow.SUCCESS_RADIUS_M`, 0.6 m), as Ilharco et al. and
VLN-CE use theirs (3 m in R2R). This module does not import :mod:`envs.follow`.

Everything here is plain numpy on ``(N, 2)`` arrays of (x, y) positions; bad input
raises a ``ValueError`` that names the parameter and what it may be.

Examples:
    An L-shaped route and an agent that cuts the corner: it succeeds on a shorter
    path, and nDTW says that it did not follow the route.

    >>> route = np.array([[0.0, 0.0], [1.5, 0.0], [3.0, 0.0], [3.0, 1.5], [3.0, 3.0]])
    >>> shortcut = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    >>> scores = path_fidelity(shortcut, route, success=True, threshold_m=0.6)
    >>> {key: round(value, 3) for key, value in scores.items()}
    {'ndtw': 0.225, 'sdtw': 0.225, 'path_length_ratio': 0.707}
    >>> path_fidelity(route, route, success=True, threshold_m=0.6)
    {'ndtw': 1.0, 'sdtw': 1.0, 'path_length_ratio': 1.0}
"""

from __future__ import annotations

import logging
import numbers

import numpy as np

from envs.expert import WALL_CONTACT_TOLERANCE_M

logger = logging.getLogger(__name__)

#: Keys of :func:`path_fidelity`'s result, in order.
PATH_FIDELITY_KEYS = ("ndtw", "sdtw", "path_length_ratio")
#: A reference route shorter than this (sum of its segment lengths, metres) does not
#: move: it has no path-length ratio (:func:`path_length_ratio` raises). A micrometre:
#: far below any step the simulator takes (forward steps are 0.3 m) and far above
#: rounding. Routes given or sampled for the follow task always move (their start is
#: outside the success radius of their end).
MIN_REFERENCE_LENGTH_M = 1e-6
#: Columns of a path: x and y, metres.
XY_COLUMNS = 2


def _check_xy(name: str, xy: object) -> np.ndarray:
    """``xy`` as a float64 ``(N, 2)`` array with N >= 1 and finite values, or a ``ValueError`` naming ``name``."""
    try:
        array = np.asarray(xy, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be an (N, 2) array of (x, y) positions in metres, got {xy!r}.") from error
    if array.ndim != 2 or array.shape[1] != XY_COLUMNS or len(array) == 0:
        raise ValueError(f"{name} must be an (N, 2) array of (x, y) positions in metres with N >= 1, got shape {array.shape}.")
    if not np.all(np.isfinite(array)):
        bad = int(np.count_nonzero(~np.isfinite(array)))
        raise ValueError(f"{name} must hold finite positions (metres), got {bad} non-finite value(s).")
    return array


def _check_positive(name: str, value: object) -> float:
    """``value`` as a float if it is a finite real number > 0, or a ``ValueError`` naming ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) or not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0 (metres), got {value!r}.")
    return float(value)


def _check_success(value: object) -> np.ndarray:
    """``value`` as a float array of 0s and 1s if it holds bools (or 0/1 numbers), or a ``ValueError``."""
    array = np.asarray(value)
    if array.dtype == np.bool_:
        return array.astype(np.float64)
    if array.dtype.kind in "iuf" and array.size and np.all((array == 0) | (array == 1)):
        return array.astype(np.float64)
    raise ValueError(f"success must be a bool or an array of bools (True/False or 1/0), got {value!r}.")


def drop_repeats(xy: np.ndarray) -> np.ndarray:
    """``xy`` without the points that equal the point before them (turns and waits on the spot).

    VLN-CE records an agent's position only when it has moved; :func:`path_fidelity`
    does the same with both paths, so that turning on the spot neither costs nor
    pads the reference's point count.

    Args:
        xy: ``(N, 2)`` positions, metres (N >= 1).

    Returns:
        ``(K, 2)`` positions, 1 <= K <= N, the first kept.

    Raises:
        ValueError: ``xy`` is not a non-empty ``(N, 2)`` array of finite values.

    Examples:
        >>> drop_repeats(np.array([[0.0, 0.0], [0.0, 0.0], [0.3, 0.0], [0.3, 0.0], [0.0, 0.0]])).tolist()
        [[0.0, 0.0], [0.3, 0.0], [0.0, 0.0]]
    """
    xy = _check_xy("xy", xy)
    keep = np.ones(len(xy), dtype=bool)
    keep[1:] = np.any(xy[1:] != xy[:-1], axis=1)
    return xy[keep]


def dtw_distance(path_xy: np.ndarray, reference_xy: np.ndarray) -> float:
    """Dynamic time warping distance between a path and a reference route, metres.

    The least sum of point distances (Euclidean, horizontal) over warping paths
    that match the first points together, the last points together, and advance
    through both sequences in order, one point or both at a time:
    ``D[i, j] = |p_i - r_j| + min(D[i-1, j], D[i, j-1], D[i-1, j-1])``, ``DTW = D[N-1, M-1]``.

    Vectorised over rows: with ``c = cost[i, :]`` and ``a[j] = c[j] + min(D[i-1, j],
    D[i-1, j-1])`` (``a[0] = c[0] + D[i-1, 0]``), the sequential ``D[i, j-1]`` term is
    closed exactly by ``D[i, :] = S + minimum.accumulate(a - S)`` where ``S = cumsum(c)``.
    The loop runs over the shorter of the two paths (DTW is symmetric); memory is the
    ``N x M`` cost matrix.

    Args:
        path_xy: ``(N, 2)`` positions of the agent, metres (N >= 1).
        reference_xy: ``(M, 2)`` positions of the reference route, metres (M >= 1).

    Returns:
        The DTW distance (>= 0, metres); 0 iff every point of each is matched only
        with equal points of the other.

    Raises:
        ValueError: either is not a non-empty ``(N, 2)`` array of finite values.

    Examples:
        >>> reference = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
        >>> dtw_distance(reference, reference)
        0.0
        >>> round(dtw_distance(reference + [0.0, 0.3], reference), 6)  # 3 points, 0.3 m off each
        0.9
        >>> dtw_distance(reference[[0, 0, 1, 1, 1, 2]], reference)  # waiting costs nothing
        0.0
    """
    path_xy = _check_xy("path_xy", path_xy)
    reference_xy = _check_xy("reference_xy", reference_xy)
    cost = np.hypot(path_xy[:, None, 0] - reference_xy[None, :, 0], path_xy[:, None, 1] - reference_xy[None, :, 1])
    if cost.shape[0] > cost.shape[1]:
        cost = cost.T
    row = np.cumsum(cost[0])
    a = np.empty(cost.shape[1])
    for c in cost[1:]:
        a[0] = c[0] + row[0]
        a[1:] = c[1:] + np.minimum(row[1:], row[:-1])
        cumulative = np.cumsum(c)
        row = cumulative + np.minimum.accumulate(a - cumulative)
    distance = float(row[-1])
    return distance if distance > 0.0 else 0.0  # no rounding below 0, no -0.0


def ndtw(path_xy: np.ndarray, reference_xy: np.ndarray, threshold_m: float) -> float:
    """Normalised DTW: ``exp(-DTW / (len(reference_xy) * threshold_m))``, in (0, 1].

    1 iff the path matches the reference point by point under DTW (:func:`dtw_distance`
    is 0); a path that keeps about ``threshold_m`` from the route scores about
    ``exp(-1)``. The points are taken as given (see :func:`drop_repeats`).

    Args:
        path_xy: ``(N, 2)`` positions of the agent, metres (N >= 1).
        reference_xy: ``(M, 2)`` positions of the reference route, metres (M >= 1).
        threshold_m: distance scale, metres (> 0): callers pass the follow protocol's
            success radius (:data:`envs.follow.SUCCESS_RADIUS_M`, 0.6 m).

    Returns:
        nDTW in (0, 1] (it may round to 0.0 for a path very far from the route).

    Raises:
        ValueError: a path is not a non-empty ``(N, 2)`` array of finite values, or
            ``threshold_m`` is not a finite number > 0.

    Examples:
        >>> reference = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
        >>> ndtw(reference, reference, threshold_m=0.6)
        1.0
        >>> round(ndtw(reference + [0.0, 0.3], reference, threshold_m=0.6), 4)  # exp(-0.9 / (3 * 0.6))
        0.6065
    """
    threshold_m = _check_positive("threshold_m", threshold_m)
    distance = dtw_distance(path_xy, reference_xy)
    return float(np.exp(-distance / (len(reference_xy) * threshold_m)))


def sdtw(success: bool | np.ndarray, ndtw_value: float | np.ndarray) -> float | np.ndarray:
    """Success weighted by nDTW: ``success * ndtw_value`` (0 on a failed episode).

    Args:
        success: whether each episode succeeded: a bool or an array of bools (1/0 too).
        ndtw_value: nDTW of each episode (:func:`ndtw`), in [0, 1]; a scalar or an
            array that broadcasts with ``success``.

    Returns:
        A float for scalar inputs, else a float64 array of the broadcast shape.

    Raises:
        ValueError: ``success`` is not bools (or 1/0), ``ndtw_value`` is not finite
            and within [0, 1], or their shapes do not broadcast.

    Examples:
        >>> sdtw(True, 0.8), sdtw(False, 0.8)
        (0.8, 0.0)
        >>> sdtw(np.array([True, False, True]), np.array([0.5, 0.9, 1.0])).tolist()
        [0.5, 0.0, 1.0]
    """
    weight = _check_success(success)
    try:
        values = np.asarray(ndtw_value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"ndtw_value must be a number or an array of numbers in [0, 1], got {ndtw_value!r}.") from error
    if not np.all(np.isfinite(values)) or np.any(values < 0) or np.any(values > 1):
        raise ValueError(f"ndtw_value must be finite and in [0, 1], got {ndtw_value!r}.")
    try:
        np.broadcast_shapes(weight.shape, values.shape)
    except ValueError as error:
        raise ValueError(
            f"success and ndtw_value must have shapes that broadcast, got {weight.shape} and {values.shape}."
        ) from error
    result = weight * values
    return float(result) if result.ndim == 0 else result


def path_length(xy: np.ndarray) -> float:
    """Length of a path: the sum of its segment lengths, metres (0 for one point).

    Args:
        xy: ``(N, 2)`` positions, metres (N >= 1).

    Raises:
        ValueError: ``xy`` is not a non-empty ``(N, 2)`` array of finite values.

    Examples:
        >>> path_length(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]))
        7.0
        >>> path_length(np.array([[1.0, 2.0]]))
        0.0
    """
    xy = _check_xy("xy", xy)
    return float(np.hypot(*np.diff(xy, axis=0).T).sum())


def path_length_ratio(path_xy: np.ndarray, reference_xy: np.ndarray) -> float:
    """Length travelled over the demonstrated length: ``path_length(path_xy) / path_length(reference_xy)``.

    Below 1: the agent took a shorter path (a shortcut, or it stopped early); above
    1: a longer one. Always finite: a reference that does not move has no ratio.

    Args:
        path_xy: ``(N, 2)`` positions of the agent, metres (N >= 1).
        reference_xy: ``(M, 2)`` positions of the reference route, metres, at least
            :data:`MIN_REFERENCE_LENGTH_M` long.

    Returns:
        The ratio, >= 0.

    Raises:
        ValueError: a path is not a non-empty ``(N, 2)`` array of finite values, or
            ``reference_xy`` is shorter than :data:`MIN_REFERENCE_LENGTH_M`.

    Examples:
        >>> reference = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0]])
        >>> round(path_length_ratio(np.array([[0.0, 0.0], [3.0, 3.0]]), reference), 4)
        0.7071
    """
    travelled = path_length(_check_xy("path_xy", path_xy))
    demonstrated = path_length(_check_xy("reference_xy", reference_xy))
    if demonstrated < MIN_REFERENCE_LENGTH_M:
        raise ValueError(
            f"reference_xy must be at least MIN_REFERENCE_LENGTH_M = {MIN_REFERENCE_LENGTH_M:g} m long (sum of its segment "
            f"lengths), got {demonstrated:g} m: a reference route that does not move has no path-length ratio."
        )
    return travelled / demonstrated


def wall_hits(requested_m: np.ndarray, moved_m: np.ndarray, tolerance_m: float = WALL_CONTACT_TOLERANCE_M) -> int:
    """Number of steps whose motion a collision shortened by more than ``tolerance_m``.

    The project's notion of a step that runs into a wall
    (:class:`~envs.user_demos.RouteRecorder`): it moves less than requested minus
    :data:`~envs.expert.WALL_CONTACT_TOLERANCE_M`; a glancing contact that slides
    along a wall loses less and does not count. Turns request no displacement and
    never count.

    Args:
        requested_m: ``(T,)`` length of each step's requested displacement, metres
            (>= 0; 0.3 for a noise-free forward step, 0 for a turn or STOP).
        moved_m: ``(T,)`` distance each step moved, metres (>= 0), e.g. the distances
            travelled that :func:`~envs.demos.apply_motion` returns.
        tolerance_m: shortening allowed without counting, metres (> 0).

    Returns:
        The number of wall hits, 0 <= hits <= T.

    Raises:
        ValueError: the arrays are not 1-D, differ in shape, hold negative or
            non-finite values, or ``tolerance_m`` is not a finite number > 0.

    Examples:
        >>> wall_hits(np.array([0.3, 0.3, 0.0, 0.3]), np.array([0.3, 0.0, 0.0, 0.28]))
        1
    """
    tolerance_m = _check_positive("tolerance_m", tolerance_m)
    arrays = []
    for name, values in (("requested_m", requested_m), ("moved_m", moved_m)):
        try:
            array = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{name} must be a 1-D array of distances >= 0 (metres), got {values!r}.") from error
        if array.ndim != 1:
            raise ValueError(f"{name} must be a 1-D array of distances >= 0 (metres), one per step, got shape {array.shape}.")
        if not np.all(np.isfinite(array)) or np.any(array < 0):
            raise ValueError(f"{name} must hold finite distances >= 0 (metres), got {array.tolist()}.")
        arrays.append(array)
    requested, moved = arrays
    if requested.shape != moved.shape:
        raise ValueError(f"requested_m and moved_m must have one value per step each, got shapes {requested.shape} and {moved.shape}.")
    return int(np.count_nonzero(moved < requested - tolerance_m))


def path_fidelity(path_xy: np.ndarray, reference_xy: np.ndarray, success: bool, threshold_m: float) -> dict[str, float]:
    """nDTW, SDTW and path-length ratio of one episode (keys :data:`PATH_FIDELITY_KEYS`).

    Consecutive repeated points are dropped from both paths first (:func:`drop_repeats`,
    as VLN-CE records positions only when the agent moves), so that turns on the spot
    neither cost nor add to the reference's point count, which normalises nDTW.

    Args:
        path_xy: ``(N, 2)`` positions of the agent, metres, from its start to its end.
        reference_xy: ``(M, 2)`` positions of the demonstrated route, metres, at least
            :data:`MIN_REFERENCE_LENGTH_M` long (e.g. ``demo.poses[:, :2]``).
        success: whether the episode succeeded (a bool).
        threshold_m: nDTW's distance scale, metres (> 0): callers pass the follow
            protocol's success radius (:data:`envs.follow.SUCCESS_RADIUS_M`, 0.6 m).

    Returns:
        ``{"ndtw": ..., "sdtw": ..., "path_length_ratio": ...}``, finite floats.

    Raises:
        ValueError: bad paths (see :func:`dtw_distance`), a reference shorter than
            :data:`MIN_REFERENCE_LENGTH_M`, a ``success`` that is not a bool, or a
            ``threshold_m`` that is not a finite number > 0.

    Examples:
        >>> reference = np.array([[0.0, 0.0], [0.3, 0.0], [0.3, 0.0], [0.6, 0.0], [0.9, 0.0]])
        >>> path_fidelity(reference[[0, 0, 1, 3]], reference, success=False, threshold_m=0.6)["sdtw"]
        0.0
    """
    if np.ndim(success) != 0:
        raise ValueError(f"success must be a bool (True/False or 1/0) for one episode, got {success!r}.")
    _check_success(success)
    threshold_m = _check_positive("threshold_m", threshold_m)
    path = drop_repeats(_check_xy("path_xy", path_xy))
    reference = drop_repeats(_check_xy("reference_xy", reference_xy))
    ratio = path_length_ratio(path, reference)
    ndtw_value = ndtw(path, reference, threshold_m)
    scores = {"ndtw": ndtw_value, "sdtw": float(sdtw(success, ndtw_value)), "path_length_ratio": ratio}
    logger.debug("path fidelity of %d points against %d: %s", len(path), len(reference), scores)
    return scores
