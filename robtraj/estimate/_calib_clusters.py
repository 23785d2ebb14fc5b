"""The clusters of a bundle fit's cluster-robust covariance (`robust_covariance`): each
static dwell of the robot is one cluster, the frames in motion between dwells form
clusters of `CLUSTER_SPAN` seconds or more (a model error is shared by neighbouring
frames)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ._calib_data import CalibrationData
from ._calib_frames import TrackerFrames
from ._calib_init import dwells

#: [s] frames in motion form clusters of this span in the robust covariance (a static
#: dwell is one cluster): a model error is shared by neighbouring frames; longer for
#: long recordings, so that there are at most `MAX_CLUSTERS`
CLUSTER_SPAN = 0.25
MAX_CLUSTERS = 400
#: the cluster-robust covariance needs a `(P, P)` matrix per frame of a chunk and per
#: cluster: above this many global parameters (a joint angle error map has hundreds) it
#: is not computed and the Gauss–Newton (posterior) covariance is reported alone
ROBUST_MAX_GLOBAL = 400


def robust_affordable(q: int, say: Callable[[str], None]) -> bool:
    """Whether the cluster-robust covariance is computed for `q` global parameters
    (`ROBUST_MAX_GLOBAL`); says so where it is not."""
    if q > ROBUST_MAX_GLOBAL:
        say(f"{q} global parameters: Gauss–Newton covariance only (no cluster-robust σ)")
        return False
    return True


def frame_clusters(data: CalibrationData, tracker: TrackerFrames) -> tuple[np.ndarray, int]:
    """Cluster index (int32) of every chunked frame `(chunks, chunk)` for the robust
    covariance, and the cluster count (padding frames: cluster 0, they carry no weight)."""
    span = max(CLUSTER_SPAN, float(data.time[-1] - data.time[0]) / (MAX_CLUSTERS - 1))
    label = np.floor((data.time - data.time[0]) / span).astype(np.int64)
    for k, frames in enumerate(dwells(data, 0.2)):
        label[frames] = -1 - k
    _, ids = np.unique(label, return_inverse=True)
    k, size = tracker.n_chunks, tracker.size
    out = np.zeros(k * size, np.int32)
    out[: ids.size] = ids
    return out.reshape(k, size), int(ids.max()) + 1


def padded_clusters(n_clusters: int) -> int:
    """The cluster count as a static shape of the clustered kernel: padded so that
    recordings of one shape share a compilation (the empty clusters are cut before the
    jackknife)."""
    return -(-n_clusters // 64) * 64
