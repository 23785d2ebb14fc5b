"""The model-error field (`field_covariance`) of a fit whose observations come in
clusters that share the robot's configuration (a bundle calibration's static dwells and
short stretches of motion), from each cluster's normal matrix ``H_g = J_gᵀW J_g`` and
score ``s_g = J_gᵀW r_g`` alone: no observation is visited again.

The field's value is taken as one displacement of every LED of a cluster (the arm's
error moves the tool; its rotation over the tool's few centimetres is small beside it).
Summing the observations of cluster g against a unit displacement along axis c gives the
field's rows and the residual exactly: with the camera←base translation ``t_c`` (a
displacement of every LED along a camera axis), ``Σ_i w_i J_iᵀ e_c = H_g[:, t_c]`` and
``Σ_i w_i e_cᵀ r_i = s_g[t_c]``. The white part of a sum has variance ``s² m_g``,
``m_g = Σ_i w_i / w_ref`` (w_ref a typical weight), its field part is ``m_g f_c(x_g)``:
divided by ``√m_g``, a cluster is a point of white variance s² and field amplitude
``√m_g``. The kernel is exact for a dwell (one configuration) and takes a stretch of
motion at its mean configuration.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

from ._model_error import ModelErrorField, field_covariance


def cluster_field(
    h: Float[np.ndarray, "p p"],
    free: Bool[np.ndarray, " p"],
    cluster_h: Float[np.ndarray, "g p p"],
    scores: Float[np.ndarray, "g p"],
    joints: Float[np.ndarray, "g joints"],
    weight: Float[np.ndarray, " g"],
    weight_ref: float,
    translation: Int[np.ndarray, " 3"],
) -> tuple[ModelErrorField, np.ndarray] | None:
    """The model-error field over the clusters' mean `joints` [rad] and the covariance
    `(p, p)` of the free parameters under it (zero elsewhere; θ's units, scaled by the
    white variance of the sums), or None where the clusters are too few to estimate it
    (fewer than the free parameters).

    `weight` `(g,)`: the sum of each cluster's observation weights [1/m²]; `weight_ref`:
    an observation's typical weight (the field's variances are relative to its noise);
    `translation`: θ's entries of a unit displacement of every observation along the
    three camera axes (camera←base's translation)."""
    cols = np.flatnonzero(free)
    if cluster_h.shape[0] < max(8, cols.size):
        return None
    root = np.sqrt(weight)
    rows = [cluster_h[:, cols, c] / root[:, None] for c in translation]
    residual = np.stack([scores[:, c] / root for c in translation])
    # the white variance of the sums: their residual once the model's columns are out
    a, y = np.concatenate(rows), residual.reshape(-1)
    beta = np.linalg.lstsq(a, y, rcond=None)[0]
    s2 = float(np.sum((y - a @ beta) ** 2)) / (a.shape[0] - cols.size)
    field = field_covariance(
        h[np.ix_(cols, cols)], rows, residual, joints, np.sqrt(weight / weight_ref)
    )
    cov = np.zeros(h.shape)
    cov[np.ix_(cols, cols)] = s2 * field.covariance
    return field, cov
