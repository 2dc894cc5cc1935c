"""Networks of the learned methods: latent chain, PointNet pose decoder, occupancy MLP.

One code path serves the three variants (see `Variant`); only the latent part differs:

* ``strep``: per-frame latents ``z~_k ~ N(0, 1)`` linked through time by a learnable
  elementwise weight ``w``: ``z_1 = z~_1``, ``z_k = z~_k + w * z_{k-1}`` (paper, Sec. 3.2);
* ``strep-nolink``: the same latents without the link (``z_k = z~_k``; no ``w`` parameter);
* ``deepmapping``: no latent; the pose comes from the frame's points alone (Ding & Feng 2019).

The link weight ``w`` starts at ``ModelConfig.link_init`` (0.5) in every entry: a memory that
halves every frame, so the chain's variance stays bounded (``1 / (1 - w^2)``: 1.33) over any
sequence length, where ``w = 1`` would make ``z_k`` a random walk whose scale grows with
``sqrt(k)`` and ``|w| > 1`` would explode. ``w`` itself is free (the paper's learnable
vector), not clamped.

Rotations: 2D corrections are ``(x, y, theta)``; 3D corrections are ``(t, omega)`` with
``omega`` an axis-angle vector mapped by the exact exponential map (Rodrigues, with Taylor
terms near zero): minimal, no singularity near the identity where corrections live, and
``omega = 0`` is the identity, so a zero-initialised last layer starts at the warm start.

All lengths are *normalised*: local points and translations are divided by the sequence's
`scale` before they reach a network, so the same widths and learning rates work in pixels
and in metres. Networks return values and keep no state between calls.
"""

from __future__ import annotations

import itertools
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from strep_core import geometry as g
from strep_core.config import ModelConfig

Variant = Literal["strep", "strep-nolink", "deepmapping"]
Composition = Literal["local", "world"]


def pose_vector_size(dim: int) -> int:
    """Entries of a pose vector: 3 in 2D ``(x, y, theta)``, 6 in 3D ``(t, axis-angle)``."""
    return 3 if dim == 2 else 6


# --------------------------------------------------------------------------------------------
# Latents


def linked_chain(raw: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The linear recurrence ``z_0 = raw_0``, ``z_k = raw_k + w * z_{k-1}`` for every frame.

    Computed as an inclusive parallel scan (Hillis-Steele): ``ceil(log2 K)`` vector steps
    ``z_k += w^s z_{k-s}`` for ``s = 1, 2, 4, ...``, so the chain over the whole sequence
    costs ``O(K b log K)`` with no Python loop over frames, and gradients reach every earlier
    ``raw_j`` and ``w``.

    Args:
        raw: ``(K, b)`` free latents ``z~``.
        w: ``(b,)`` elementwise link weight.

    Returns:
        ``(K, b)`` linked latents ``z``.
    """
    z = raw
    power = w
    step = 1
    k = raw.shape[0]
    while step < k:
        z = torch.cat([z[:step], z[step:] + power * z[:-step]], 0)
        power = power * power
        step *= 2
    return z


class Latents(nn.Module):
    """Per-frame latent vectors, linked (``strep``) or not (``strep-nolink``).

    Parameters: ``raw (K, b)`` drawn from ``N(0, 1)``; ``w (b,)`` only when linked,
    initialised to ``w_init`` in every entry.
    """

    def __init__(self, num_frames: int, dim: int, *, linked: bool, w_init: float) -> None:
        super().__init__()
        self.raw = nn.Parameter(torch.randn(num_frames, dim))
        self.w = nn.Parameter(torch.full((dim,), float(w_init))) if linked else None

    def forward(self, upto: int | None = None) -> torch.Tensor:
        """``(n, b)`` latents of frames ``0 .. n-1`` (``n = upto``, default every frame).

        The chain always starts at frame 0: ``z_k`` of a batch that ends at frame ``n - 1`` is the
        whole sequence's ``z_k`` (the same numbers), and its gradient reaches every earlier ``z~_j``.
        """
        raw = self.raw if upto is None or upto >= len(self.raw) else self.raw[:upto]
        if self.w is None:
            return raw
        return linked_chain(raw, self.w)


# --------------------------------------------------------------------------------------------
# Pose decoder


class _BatchNorm(nn.BatchNorm1d):
    """BatchNorm over every leading axis: ``(..., C)`` normalised per channel ``C``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.reshape(-1, x.shape[-1])).view(x.shape)


def _mlp(sizes: list[int], *, batch_norm: bool = False) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in itertools.pairwise(sizes):
        layers += [nn.Linear(a, b), *([_BatchNorm(b)] if batch_norm else []), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


def _per_point(layer: nn.Module, h: torch.Tensor) -> torch.Tensor:
    """``layer`` (Linear, BatchNorm, ReLU or Identity, as built for ``(..., C)`` rows) applied to
    every point of channels-first ``h (B, C, N)``."""
    if isinstance(layer, nn.Linear):
        return F.conv1d(h, layer.weight[..., None], layer.bias)
    if isinstance(layer, nn.BatchNorm1d):  # (B, C, N): statistics per channel over frames and points
        return nn.BatchNorm1d.forward(layer, h)
    return layer(h)


class PoseDecoder(nn.Module):
    """PointNet-style regression of a pose-correction vector per frame.

    Per point: ``[x_i, z_k]`` -> shared layers ``point_layers`` (Linear + ReLU, i.e. a
    kernel-1 convolution over points) -> max-pool over the frame's points -> fully
    connected ``head_layers`` (Linear + ReLU) -> a last Linear to the pose vector, zero
    initialised so that every correction starts at exactly the identity.

    The paper's text says "1D convolution with kernel size 3": over an unordered point set a
    kernel wider than 1 would mix arbitrary neighbours in storage order, so the layers are
    per point, as in PointNet and DeepMapping. Optional BatchNorm after every layer
    (``batch_norm``; off by default: it couples the frames of a batch and measured worse).

    The first layer is split as ``W [x; z] = W_x x + W_z z``: the latent term is computed
    once per frame and broadcast to its points (the same function as concatenating ``z``
    to every point, without the ``(B, N, D + b)`` tensor).
    """

    def __init__(
        self,
        dim: int,
        latent_dim: int,
        point_layers: list[int],
        head_layers: list[int],
        *,
        batch_norm: bool = False,
    ) -> None:
        super().__init__()
        self.dim = dim
        self.latent_dim = latent_dim
        self.first_points = nn.Linear(dim, point_layers[0])
        self.first_norm = _BatchNorm(point_layers[0]) if batch_norm else nn.Identity()
        self.point_mlp = _mlp(point_layers, batch_norm=batch_norm)
        self.head = _mlp([point_layers[-1], *head_layers], batch_norm=batch_norm)
        self.out = nn.Linear(([point_layers[-1], *head_layers])[-1], pose_vector_size(dim))
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        # Built last, so the shared layers draw the same random numbers in every variant.
        self.first_latent = nn.Linear(latent_dim, point_layers[0], bias=False) if latent_dim else None

    def forward(self, points: torch.Tensor, latent: torch.Tensor | None) -> torch.Tensor:
        """Pose-correction vectors of a batch of frames.

        Args:
            points: ``(B, N, D)`` normalised local points (frames with fewer points are
                padded by repeating their own points, which max-pooling ignores).
            latent: ``(B, b)`` latents, or ``None`` for the ``deepmapping`` variant.

        Returns:
            ``(B, 3)`` ``(x, y, theta)`` in 2D or ``(B, 6)`` ``(t, axis-angle)`` in 3D;
            translations in normalised units, angles in radians.
        """
        # The per-point layers run channels first, (B, C, N), as kernel-1 convolutions with the
        # Linear layers' own weights, and max-pool over the contiguous point axis before the last
        # ReLU (relu(max) = max(relu)): the same function as Linear + ReLU on (B, N, C) then amax,
        # with decoder forward + backward about 2x cheaper on a CPU (docs/design/optimiser.md).
        h = _per_point(self.first_points, points.transpose(1, 2))
        if self.first_latent is not None:
            if latent is None:
                raise ValueError("this decoder was built for latents; pass them")
            h = h + self.first_latent(latent)[:, :, None]
        h = torch.relu(_per_point(self.first_norm, h))
        for layer in list(self.point_mlp)[:-1]:  # the last ReLU waits until after the pool
            h = _per_point(layer, h)
        feature = torch.relu(h.max(dim=2).values)
        return self.out(self.head(feature))


# --------------------------------------------------------------------------------------------
# Occupancy


class OccupancyMLP(nn.Module):
    """Occupancy logit of world positions: ``layers`` (Linear + ReLU) then Linear to 1.

    Input: ``(P, D)`` normalised world coordinates (centred on the initial trajectory).
    Output: ``(P,)`` logits (occupied > 0).
    """

    def __init__(self, dim: int, layers: list[int]) -> None:
        super().__init__()
        self.body = _mlp([dim, *layers])
        self.out = nn.Linear(layers[-1], 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.body(x))[..., 0]


# --------------------------------------------------------------------------------------------
# Pose composition


def correction_pose(vector: torch.Tensor, *, translation_scale: float = 1.0) -> torch.Tensor:
    """Homogeneous correction ``(B, D+1, D+1)`` from decoder outputs ``(B, 3|6)``.

    The translation part is multiplied by ``translation_scale`` (normalised units); the
    rotation part is an angle (2D) or an axis-angle vector (3D, exact exponential map,
    smooth with finite gradients at the identity).
    """
    d = 2 if vector.shape[-1] == 3 else 3
    v = torch.cat([vector[..., :d] * translation_scale, vector[..., d:]], -1)
    return g.pose_from_vector(v)


def planar_vector(vector: torch.Tensor, axis: list[float]) -> torch.Tensor:
    """3D pose vectors ``(B, 6)`` = ``(t, omega)`` limited to turns about ``axis`` and moves across it.

    A level camera (`ModelConfig.planar_axis`): applied to the corrections of poses that are
    level already (identity), every pose stays level.
    """
    v = torch.as_tensor(axis, dtype=vector.dtype, device=vector.device)
    v = v / v.norm()
    t, w = vector[..., :3], vector[..., 3:]
    return torch.cat([t - (t @ v)[..., None] * v, (w @ v)[..., None] * v], -1)


def compose_correction(init: torch.Tensor, corr: torch.Tensor, *, composition: Composition) -> torch.Tensor:
    """Apply corrections ``corr (B, D+1, D+1)`` to warm-start poses ``init (B, D+1, D+1)``.

    * ``"local"``: ``init @ corr``: the correction acts in the sensor's own frame, so its
      rotation turns the frame about its sensor origin and its translation is expressed in
      the frame's axes.
    * ``"world"``: rotation about the frame's local origin (its sensor, for data whose
      sensor origins are zero), translation along the world axes: ``R = R_c R_0``,
      ``t = t_0 + t_c``.
    """
    if composition == "local":
        return init @ corr
    d = init.shape[-1] - 1
    out = init.clone()
    out[..., :d, :d] = corr[..., :d, :d] @ init[..., :d, :d]
    out[..., :d, d] = init[..., :d, d] + corr[..., :d, d]
    return out


# --------------------------------------------------------------------------------------------
# One run's model: latents + decoder + occupancy


class StrepModel(nn.Module):
    """Latents (per variant), pose decoder and occupancy MLP of one run.

    ``forward(decoder_points, frames, latents)`` returns correction vectors; the latents
    are computed once per step by ``self.latents(upto)``, from frame 0 to the batch's last
    frame (the chain spans every earlier frame, so a batch's loss reaches them through ``w``).
    """

    def __init__(self, variant: Variant, dim: int, num_frames: int, cfg: ModelConfig) -> None:
        super().__init__()
        self.variant = variant
        latent_dim = latent_size(cfg, dim) if variant != "deepmapping" else 0
        # Built in this order so that every variant draws the same random numbers for the
        # shared networks (the decoder creates its latent layer last).
        self.occupancy = OccupancyMLP(dim, cfg.occupancy_layers)
        self.decoder = PoseDecoder(dim, latent_dim, cfg.point_layers, cfg.head_layers, batch_norm=cfg.batch_norm)
        self.latents = (
            Latents(num_frames, latent_dim, linked=variant == "strep", w_init=cfg.link_init) if latent_dim else None
        )

    def all_latents(self, upto: int | None = None) -> torch.Tensor | None:
        """``(K, b)`` latents of every frame (of frames ``0 .. upto-1`` if given), or ``None`` (deepmapping)."""
        return None if self.latents is None else self.latents(upto)

    def forward(self, decoder_points: torch.Tensor, frames: torch.Tensor, latents: torch.Tensor | None) -> torch.Tensor:
        """Correction vectors ``(B, 3|6)`` of ``frames (B,)`` from their ``(B, Nd, D)`` points."""
        z = None if latents is None else latents.index_select(0, frames)
        return self.decoder(decoder_points, z)


def latent_size(cfg: ModelConfig, dim: int) -> int:
    """Latent dimension: the config's, else 16 in 2D and 24 in 3D (paper)."""
    return cfg.latent_dim if cfg.latent_dim is not None else (16 if dim == 2 else 24)
