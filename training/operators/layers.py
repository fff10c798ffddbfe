"""Building blocks: MLPs, an ONNX-friendly truncated-DFT spectral convolution, Gram-Schmidt, geometry."""

from __future__ import annotations

import math

import torch
from torch import nn

from tdcr import design_space
from tdcr.robot.designs import LOAD_COLUMNS


def mlp(sizes: list[int], activation: type[nn.Module], dropout: float = 0.0) -> nn.Sequential:
    """Linear layers of the given sizes with ``activation`` (and optional dropout) between them; last is linear."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=False)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(activation())
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
    return nn.Sequential(*layers)


def dft_bases(n: int, modes: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Real bases of the truncated rfft / irfft on ``n`` points, keeping rfft bins 0..modes-1.

    Forward:  X_k = sum_j x_j exp(-2 pi i j k / n)  ->  Re = x @ cos, Im = -(x @ sin), each ``(n, modes)``.
    Inverse (irfft of a spectrum that is zero above ``modes``, n > 2 (modes - 1)):
        x_j = (1/n) [Re X_0 + 2 sum_{k>=1} (Re X_k cos - Im X_k sin)]  ->  ``(modes, n)`` bases.
    """
    j = torch.arange(n, dtype=torch.float64)[:, None]
    k = torch.arange(modes, dtype=torch.float64)[None, :]
    angle = 2.0 * math.pi * j * k / n
    fwd_cos, fwd_sin = torch.cos(angle), -torch.sin(angle)
    weight = torch.full((modes,), 2.0, dtype=torch.float64)
    weight[0] = 1.0
    inv_cos = (weight[:, None] * torch.cos(angle).T) / n
    inv_sin = -(weight[:, None] * torch.sin(angle).T) / n
    return fwd_cos.float(), fwd_sin.float(), inv_cos.float(), inv_sin.float()


class SpectralConv1d(nn.Module):
    """Fourier layer kernel on a fixed grid of ``n`` points with ``modes`` retained rfft bins.

    Equivalent to ``irfft(W * rfft(x)[:modes], n)`` along the grid axis, but written with
    precomputed cos / sin bases, so it exports to plain ONNX MatMuls and is exact (tested
    against torch.fft).

    ``mixing='shared'`` (the paper's parameter count): one real (C_in -> C_out) matrix and a bias,
    shared by all retained modes.  ``mixing='full'``: complex weights per mode (in, out, modes).

    Shapes: ``(B, n, C_in) -> (B, n, C_out)`` (channels last, so channel mixing is one GEMM).
    """

    def __init__(self, in_channels: int, out_channels: int, modes: int, n: int, mixing: str = "shared"):
        super().__init__()
        scale = 1.0 / (in_channels * out_channels)
        self.mixing = mixing
        if mixing == "shared":
            self.linear = nn.Linear(in_channels, out_channels)
        elif mixing == "full":
            self.weight_re = nn.Parameter(scale * torch.rand(in_channels, out_channels, modes))
            self.weight_im = nn.Parameter(scale * torch.rand(in_channels, out_channels, modes))
        else:
            raise ValueError(f"mixing must be 'shared' or 'full', not {mixing!r}")
        fc, fs, ic, is_ = dft_bases(n, modes)
        # transposed so that the grid axis is contracted by a shared left operand
        self.register_buffer("fwd_cos", fc.T.contiguous(), persistent=False)  # (modes, n)
        self.register_buffer("fwd_sin", fs.T.contiguous(), persistent=False)
        self.register_buffer("inv_cos", ic.T.contiguous(), persistent=False)  # (n, modes)
        self.register_buffer("inv_sin", is_.T.contiguous(), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x_re = self.fwd_cos @ x  # (B, modes, C_in)
        x_im = self.fwd_sin @ x
        if self.mixing == "shared":
            # mix channels on the retained coefficients (the matrix commutes with the inverse transform)
            w = self.linear.weight.T
            return self.inv_cos @ (x_re @ w) + self.inv_sin @ (x_im @ w) + self.linear.bias
        y_re = torch.einsum("bmi,iom->bmo", x_re, self.weight_re) - torch.einsum("bmi,iom->bmo", x_im, self.weight_im)
        y_im = torch.einsum("bmi,iom->bmo", x_re, self.weight_im) + torch.einsum("bmi,iom->bmo", x_im, self.weight_re)
        return self.inv_cos @ y_re + self.inv_sin @ y_im  # (B, n, C_out)

    def forward_batch_last(self, x: torch.Tensor) -> torch.Tensor:
        """The same map with channels first and the batch last, ``(C_in, n, B) -> (C_out, n, B)``
        (``mixing='shared'``): the grid axis is contracted by MatMuls broadcast over channels and
        the channels are mixed by one GEMM over all retained coefficients and designs."""
        fwd = torch.cat([self.fwd_cos, self.fwd_sin])  # (2 modes, n): Re and Im rows
        inv = torch.cat([self.inv_cos, self.inv_sin], dim=1)  # (n, 2 modes)
        c_in, _, b = x.shape
        coeffs = torch.matmul(fwd, x)  # (C_in, 2 modes, B)
        mixed = torch.matmul(self.linear.weight, coeffs.reshape(c_in, -1)).reshape(-1, fwd.shape[0], b)
        return torch.matmul(inv, mixed) + self.linear.bias[:, None, None]


def gram_schmidt(a1: torch.Tensor, a2: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from two vectors ``(..., 3)``: columns b1, b2, b1 x b2 (Gram-Schmidt).  ``(..., 3, 3)``."""
    b1 = a1 / torch.linalg.vector_norm(a1, dim=-1, keepdim=True).clamp_min(1e-12)
    u2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = u2 / torch.linalg.vector_norm(u2, dim=-1, keepdim=True).clamp_min(1e-12)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


# log(E I) over Table I: E I from 15.5e9 * pi (5e-4)^4 / 4 to 45.5e9 * pi (1.5e-3)^4 / 4 (N m^2)
_LOG_EI_LOW = math.log(15.5e9 * math.pi * 5e-4**4 / 4)
_LOG_EI_HIGH = math.log(45.5e9 * math.pi * 1.5e-3**4 / 4)
_LOG_EI_MID, _LOG_EI_HALF = (_LOG_EI_LOW + _LOG_EI_HIGH) / 2, (_LOG_EI_HIGH - _LOG_EI_LOW) / 2


#: The trained load magnitudes ``[low, high]`` (:data:`tdcr.robot.design_space.TRAINING_LOADS`), input scales.
_LOAD_RANGES = design_space.TRAINING_LOADS.ranges()
#: Network inputs per load vector (:meth:`DesignGeometry.load_features`).
N_LOAD_FEATURES = 18


class DesignGeometry(nn.Module):
    """Undeformed-robot geometry and input normalisation, inside the graph.

    ``features`` are raw SI designs ``(B, 3 + 3 N_t)`` = [E, r, L, offsets, pitches, tensions].
    """

    def __init__(self, low: torch.Tensor, high: torch.Tensor, n_tendons: int):
        super().__init__()
        self.n_tendons = n_tendons
        self.register_buffer("low", low.float())
        self.register_buffer("high", high.float())
        self.register_buffer("base_angle", 2.0 * math.pi * torch.arange(n_tendons, dtype=torch.float32) / n_tendons)

    def normalize(self, features: torch.Tensor) -> torch.Tensor:
        """Affine map of the Table I box onto [-1, 1]; ``(B, F) -> (B, F)``."""
        return 2.0 * (features - self.low) / (self.high - self.low) - 1.0

    def physics_features(self, features: torch.Tensor) -> torch.Tensor:
        """Dimensionless groups of the linearised (small-deflection) model, ``(B, 2 N_t + 3)``.

        a_i = tau_i rho_i L / (E I) (bending angle a tendon alone would cause, rad, scaled by 1/10),
        the linearised bending vector sum_i a_i [cos, sin](2 pi i / N_t), log(E I) mapped over
        Table I onto [-1, 1], and pitch_i L / 7.
        """
        t = self.n_tendons
        e, r, length = features[:, 0:1], features[:, 1:2], features[:, 2:3]
        offset, pitch, tension = features[:, 3:3 + t], features[:, 3 + t:3 + 2 * t], features[:, 3 + 2 * t:]
        ei = e * (math.pi / 4.0) * r**4
        a = tension * offset * length / ei / 10.0  # (B, N_t)
        bend = torch.stack([(a * torch.cos(self.base_angle)).sum(1), (a * torch.sin(self.base_angle)).sum(1)], dim=1)
        log_ei = (torch.log(ei) - _LOG_EI_MID) / _LOG_EI_HALF
        return torch.cat([a, bend, log_ei, pitch * length / 7.0], dim=1)

    def load_features(self, features: torch.Tensor, loads: torch.Tensor) -> torch.Tensor:
        """Network inputs of the loads ``(B, 10)`` (gravity, density, tip force, tip moment, base
        frame, SI), ``(B, 18)``: the small-deflection groups w L^3 / (E I) (weight per length
        w = rho pi r^2 g), F L^2 / (E I) and M L / (E I), each a 3-vector of about unit size over the
        training loads, then g, F and M over their largest trained magnitudes."""
        e, r, length = features[:, 0:1], features[:, 1:2], features[:, 2:3]
        ei = e * (math.pi / 4.0) * r**4
        gravity, density, force, moment = (loads[:, LOAD_COLUMNS[k]] for k in ("gravity", "density", "tip_force",
                                                                              "tip_moment"))
        weight = gravity * density * (math.pi * r * r)  # (B, 3) N/m
        return torch.cat([weight * length**3 / ei, force * length**2 / ei, moment * length / ei,
                          gravity / _LOAD_RANGES["gravity"][1], force / _LOAD_RANGES["tip_force"][1],
                          moment / _LOAD_RANGES["tip_moment"][1]], dim=1)

    def rho(self, features: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
        """Body-frame tendon offsets rho_i(s), m, ``(B, n, N_t, 3)`` at the arclength ``fractions`` ``(n,)`` of L."""
        t = self.n_tendons
        length = features[:, 2:3]  # (B, 1)
        offset = features[:, 3:3 + t][:, None, :]  # (B, 1, N_t)
        pitch = features[:, 3 + t:3 + 2 * t][:, None, :]
        s = length * fractions[None, :]  # (B, n) m
        phi = self.base_angle + pitch * s[:, :, None]  # (B, n, N_t)
        return torch.stack([offset * torch.cos(phi), offset * torch.sin(phi), torch.zeros_like(phi)], dim=-1)

    def undeformed_tendons(self, features: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
        """Tendon positions of the straight rod, m, ``(B, n, N_t, 3)``."""
        rho = self.rho(features, fractions)
        z = (features[:, 2:3] * fractions[None, :])[:, :, None, None]  # (B, n, 1, 1)
        return rho + torch.cat([torch.zeros_like(z), torch.zeros_like(z), z], dim=-1)
