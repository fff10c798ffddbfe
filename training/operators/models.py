"""The four operators of the paper (Section III) and a registry of them by name.

Every model maps raw SI designs ``(B, 3 + 3 N_t)`` to SI outputs: normalisation, the reference
robot, Gram-Schmidt and the tendon geometry are inside the module (and so inside the exported
ONNX graph).  The networks predict the deviation from a reference robot (``reference``):

* ``'undeformed'`` (the paper's): the straight rod, p_0 = (0, 0, s), R_0 = I; outputs in units of L.
* ``'linearized'`` (tuned preset): the rod integrated from the first-order strains of the local
  equilibrium (:mod:`training.operators.kinematics`); outputs in units of L / 100.

* tendon models (G'):  tendons = p_0 + R_0 rho_i(s) + L * net(d, s)            ``(B, n, N_t, 3)``
* pose models (G):     p = p_0 + L * net_p,  R = R_0 GS(e1 + net_a1, e2 + net_a2),
                       tendons = p + R rho_i(s)    (paper eq. tend-path)

``forward`` returns ``tendons`` for tendon models and ``(backbone, rotation, tendons)`` for pose
models; the runtime fits the pose of tendon models (``tdcr.surrogates.runtime.rigid_fit``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from tdcr import design_space
from training.operators import kinematics
from training.operators.layers import N_LOAD_FEATURES, DesignGeometry, SpectralConv1d, gram_schmidt, mlp

N_T = design_space.N_TENDONS
N_FEATURES = 3 + 3 * N_T
#: ``reference='linearized'``: network outputs are corrections in units of this fraction of L
_LINEARIZED_SCALE = 0.01
#: grid of the linearised reference robot of DeepONets (FNOs use their own grid)
_REFERENCE_POINTS = design_space.DEFAULT_POINTS


@dataclass(frozen=True)
class DeepONetConfig:
    """Stacked DeepONet: branch MLP on the design, trunk MLP on s, ``p`` basis functions per output."""

    branch_width: int = 64
    branch_layers: int = 5
    trunk_width: int = 128
    trunk_layers: int = 5
    p: int = 100
    dropout: float = 0.0
    inputs: str = "table"
    reference: str = "undeformed"
    loads: bool = False
    load_iterations: int = 4


@dataclass(frozen=True)
class FNOConfig:
    """FNO on the fixed grid of ``n_points`` arclengths: lift, ``layers`` Fourier layers, linear projection."""

    width: int = 128
    layers: int = 5
    modes: int = 5
    n_points: int = design_space.DEFAULT_POINTS
    dropout: float = 0.0
    mixing: str = "shared"
    inputs: str = "table"
    reference: str = "undeformed"
    loads: bool = False
    load_iterations: int = 4


class _OperatorBase(nn.Module):
    """Shared output heads.  ``kind`` is 'tendons' (G') or 'pose' (G)."""

    def __init__(self, kind: str, config):
        super().__init__()
        if config.reference not in ("undeformed", "linearized"):
            raise ValueError(f"reference must be 'undeformed' or 'linearized', not {config.reference!r}")
        if kind not in ("tendons", "pose"):
            raise ValueError(f"unknown kind {kind!r}")
        if config.loads and config.reference != "linearized":
            raise ValueError("a loaded operator needs reference='linearized' (the loaded reference robot)")
        self.kind = kind
        self.out_channels = 3 * N_T if kind == "tendons" else 9
        low, high = design_space.feature_bounds(N_T)
        self.geometry = DesignGeometry(torch.as_tensor(low), torch.as_tensor(high), N_T)

    def raw(self, features: torch.Tensor, fractions: torch.Tensor, loads=None) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError

    def encode(self, features: torch.Tensor, loads: torch.Tensor | None = None) -> torch.Tensor:
        """Network input from raw SI designs: the Table I affine map (``inputs='table'``, the paper's),
        plus the linearised-model groups of :meth:`DesignGeometry.physics_features` (``'physics'``),
        plus for loaded models the load groups of :meth:`DesignGeometry.load_features` of the loads
        ``(B, 10)`` (zero when omitted)."""
        x = self.geometry.normalize(features)
        if self.config.inputs == "physics":
            x = torch.cat([x, self.geometry.physics_features(features)], dim=1)
        if self.config.loads:
            x = torch.cat([x, self.geometry.load_features(features, self._loads(features, loads))], dim=1)
        return x

    @staticmethod
    def _loads(features: torch.Tensor, loads: torch.Tensor | None) -> torch.Tensor:
        return features.new_zeros(features.shape[0], 10) if loads is None else loads

    @property
    def n_inputs(self) -> int:
        return (N_FEATURES + (2 * N_T + 3 if self.config.inputs == "physics" else 0)
                + (N_LOAD_FEATURES if self.config.loads else 0))

    def reference(self, features: torch.Tensor, fractions: torch.Tensor, loads: torch.Tensor | None = None
                  ) -> kinematics.ReferenceRobot:
        """The linearised reference robot, batch last (:class:`kinematics.ReferenceRobot`), on the
        model's grid or (DeepONet) at any ``fractions``: one Magnus step from the grid point below.
        Loaded models: the loaded reference (:func:`kinematics.loaded_reference`) of ``loads`` ``(B, 10)``."""
        grid = self.reference_grid
        at = None if fractions is grid else fractions
        if self.config.loads:
            return kinematics.loaded_reference(features, self._loads(features, loads), grid, self.geometry.base_angle,
                                               at, iterations=self.config.load_iterations)
        return kinematics.linearized_reference(features, grid, self.geometry.base_angle, at)

    def raw_batch_last(self, features: torch.Tensor, fractions: torch.Tensor, loads=None) -> torch.Tensor:
        """:meth:`raw` with the batch last, ``(C, n, B)``."""
        return self.raw(features, fractions, loads).permute(2, 1, 0)

    def outputs(self, features: torch.Tensor, fractions: torch.Tensor, ref=None, loads=None):
        """Tendons ``(B, n, N_t, 3)`` m, or (backbone, rotation, tendons) for pose models; ``loads``
        ``(B, 10)`` for loaded models."""
        if self.config.reference == "linearized":
            return self._linearized_heads(features, fractions, self.raw_batch_last(features, fractions, loads), ref,
                                          loads)
        return self.heads(features, fractions, self.raw(features, fractions), ref)

    def heads(self, features: torch.Tensor, fractions: torch.Tensor, out: torch.Tensor, ref=None, loads=None):
        """``out`` ``(B, n, C)`` -> tendons ``(B, n, N_t, 3)`` m, or (backbone, rotation, tendons).

        ``ref``: the precomputed :meth:`reference` (training caches it); computed when omitted.
        """
        if self.config.reference == "linearized":
            return self._linearized_heads(features, fractions, out.permute(2, 1, 0), ref, loads)
        length = features[:, 2:3, None]  # (B, 1, 1)
        rho = self.geometry.rho(features, fractions)  # (B, n, N_t, 3)
        if self.kind == "tendons":
            b, n = out.shape[0], out.shape[1]
            return self.geometry.undeformed_tendons(features, fractions) + length[..., None] * out.reshape(b, n, N_T, 3)
        e1 = torch.tensor([1.0, 0.0, 0.0], dtype=out.dtype, device=out.device)
        e2 = torch.tensor([0.0, 1.0, 0.0], dtype=out.dtype, device=out.device)
        s = features[:, 2:3] * fractions[None, :]  # (B, n)
        straight = torch.stack([torch.zeros_like(s), torch.zeros_like(s), s], dim=-1)
        backbone = straight + length * out[..., 0:3]
        rotation = gram_schmidt(e1 + out[..., 3:6], e2 + out[..., 6:9])  # (B, n, 3, 3)
        tendons = backbone[:, :, None, :] + torch.einsum("bnij,bntj->bnti", rotation, rho)
        return backbone, rotation, tendons

    def _linearized_heads(self, features: torch.Tensor, fractions: torch.Tensor, out: torch.Tensor, ref, loads=None):
        """The heads around the linearised reference, computed batch last (``out`` ``(C, n, B)``);
        corrections in units of L / 100; tendon channels are ordered (tendon, coordinate)."""
        if ref is None:
            ref = self.reference(features, fractions, loads)
        scale = features[:, 2] * _LINEARIZED_SCALE  # (B,) m
        n, b = out.shape[1], out.shape[2]
        if self.kind == "tendons":
            tendons = ref.tendons() + scale * out.reshape(N_T, 3, n, b)
            return kinematics.batch_first(tendons)
        e1 = torch.tensor([1.0, 0.0, 0.0], dtype=out.dtype, device=out.device)[:, None, None]
        e2 = torch.tensor([0.0, 1.0, 0.0], dtype=out.dtype, device=out.device)[:, None, None]
        backbone = ref.backbone + scale * out[0:3]
        correction = kinematics.gram_schmidt(e1 + _LINEARIZED_SCALE * out[3:6], e2 + _LINEARIZED_SCALE * out[6:9])
        rotation = kinematics.matmul3(ref.rotation, correction)
        tendons = kinematics.tendon_positions(backbone, rotation, (ref.rho_x, ref.rho_y))
        return tuple(kinematics.batch_first(x) for x in (backbone, rotation, tendons))

    def tendons(self, features: torch.Tensor, fractions: torch.Tensor, ref=None, loads=None) -> torch.Tensor:
        """Predicted tendon positions ``(B, n, N_t, 3)`` m (what both losses compare)."""
        out = self.outputs(features, fractions, ref, loads)
        return out if self.kind == "tendons" else out[2]


class DeepONet(_OperatorBase):
    """G'_DON / G_DON: out_c(d, s) = sum_k branch(d)_{c,k} trunk(s)_{c,k} + b_c (paper eq. don1, don2)."""

    def __init__(self, kind: str, config: DeepONetConfig = DeepONetConfig()):
        super().__init__(kind, config)
        self.config = config
        c, p = self.out_channels, config.p
        self.branch = mlp([self.n_inputs] + [config.branch_width] * (config.branch_layers - 1) + [c * p], nn.Tanh,
                          config.dropout)
        self.trunk = mlp([1] + [config.trunk_width] * (config.trunk_layers - 1) + [c * p], nn.Tanh, config.dropout)
        self.bias = nn.Parameter(torch.zeros(c))
        self.register_buffer("_reference_grid", torch.linspace(0.0, 1.0, _REFERENCE_POINTS), persistent=False)

    def raw(self, features: torch.Tensor, fractions: torch.Tensor, loads=None) -> torch.Tensor:
        c, p = self.out_channels, self.config.p
        b = self.branch(self.encode(features, loads)).reshape(-1, c, p)  # (B, C, p)
        t = self.trunk(2.0 * fractions[:, None] - 1.0).reshape(-1, c, p)  # (n, C, p)
        # out[b, n, c] = sum_k b[b, c, k] t[n, c, k], as one batched MatMul over c (fast in onnxruntime)
        out = torch.matmul(b.permute(1, 0, 2), t.permute(1, 2, 0))  # (C, B, n)
        return out.permute(1, 2, 0) + self.bias

    def raw_batch_last(self, features: torch.Tensor, fractions: torch.Tensor, loads=None) -> torch.Tensor:
        """:meth:`raw` as ``(C, n, B)``, with the trunk folded into the branch's last (linear) layer.

        With branch(d)_c = W_c h(d) + b_c (W_c ``(p, width)``, h the last hidden layer),
        out_c(d, s) = [trunk_c(s) W_c] h(d) + trunk_c(s) . b_c + bias_c: the bracket ``(n, width)``
        depends on s only, so each design costs C n width multiply-adds instead of
        C p (width + n) (32 k instead of 127 k for the paper's sizes), and no large transpose.
        """
        c, p = self.out_channels, self.config.p
        hidden = self.branch[:-1](self.encode(features, loads))  # (B, width)
        last = self.branch[-1]
        n = fractions.shape[0]
        t = self.trunk(2.0 * fractions[:, None] - 1.0).reshape(-1, c, p).permute(1, 0, 2)  # (C, n, p)
        folded = torch.matmul(t, last.weight.reshape(c, p, -1)).reshape(c * n, -1)  # (C n, width)
        offset = torch.matmul(t, last.bias.reshape(c, p, 1)) + self.bias[:, None, None]  # (C, n, 1)
        return (torch.matmul(folded, hidden.T) + offset.reshape(c * n, 1)).reshape(c, n, -1)

    def forward(self, features: torch.Tensor, fractions: torch.Tensor, loads: torch.Tensor | None = None):
        return self.outputs(features, fractions, loads=loads)

    @property
    def reference_grid(self) -> torch.Tensor:
        return self._reference_grid


class FNO(_OperatorBase):
    """G'_FNO / G_FNO on the grid s_j = j / (n - 1): input channels [2 s - 1, normalised design]
    ``(B, 1 + F, n)``, lifted to ``width``, ``layers`` Fourier layers (spectral + pointwise, eq. fno_int)
    with ReLU between, and a final linear map to C channels (eq. fno1)."""

    def __init__(self, kind: str, config: FNOConfig = FNOConfig()):
        super().__init__(kind, config)
        self.config = config
        w = config.width
        self.register_buffer("grid", torch.linspace(0.0, 1.0, config.n_points), persistent=False)
        self.lift = nn.Linear(1 + self.n_inputs, w)
        self.spectral = nn.ModuleList(
            SpectralConv1d(w, w, config.modes, config.n_points, config.mixing) for _ in range(config.layers)
        )
        self.pointwise = nn.ModuleList(nn.Linear(w, w) for _ in range(config.layers))
        self.dropout = nn.Dropout(config.dropout) if config.dropout > 0 else nn.Identity()
        self.project = nn.Linear(w, self.out_channels)

    def raw(self, features: torch.Tensor, fractions: torch.Tensor | None = None, loads=None) -> torch.Tensor:
        b, n = features.shape[0], self.config.n_points
        d = self.encode(features, loads)[:, None, :].expand(b, n, self.n_inputs)
        s = (2.0 * self.grid - 1.0)[None, :, None].expand(b, n, 1)
        x = self.lift(torch.cat([s, d], dim=-1))  # (B, n, W)
        for k, (spec, point) in enumerate(zip(self.spectral, self.pointwise, strict=True)):
            x = spec(x) + point(x)
            if k < len(self.spectral) - 1:
                x = self.dropout(torch.relu(x))
        return self.project(x)  # (B, n, C)

    def raw_batch_last(self, features: torch.Tensor, fractions: torch.Tensor | None = None, loads=None) -> torch.Tensor:
        """:meth:`raw` computed channels first and batch last, ``(C, n, B)``: every channel map is
        one GEMM over all points and designs, with no transpose of the ``(B, n, W)`` activations.
        The lift of [s, design] is the sum of its two parts (the design is constant along s)."""
        if self.config.mixing != "shared":
            return super().raw_batch_last(features, fractions, loads)
        n = self.config.n_points
        d = self.encode(features, loads)  # (B, F)
        w_lift = self.lift.weight  # (W, 1 + F)
        x = (w_lift[:, :1, None] * (2.0 * self.grid - 1.0)[None, :, None]  # (W, n, 1)
             + torch.matmul(w_lift[:, 1:], d.T)[:, None, :] + self.lift.bias[:, None, None])  # (W, n, B)
        for k, (spec, point) in enumerate(zip(self.spectral, self.pointwise, strict=True)):
            flat = x.reshape(x.shape[0], -1)  # (W, n B)
            pointwise = (torch.matmul(point.weight, flat) + point.bias[:, None]).reshape(-1, n, x.shape[2])
            x = spec.forward_batch_last(x) + pointwise
            if k < len(self.spectral) - 1:
                x = self.dropout(torch.relu(x))
        out = torch.matmul(self.project.weight, x.reshape(x.shape[0], -1)) + self.project.bias[:, None]
        return out.reshape(-1, n, x.shape[2])  # (C, n, B)

    def forward(self, features: torch.Tensor, loads: torch.Tensor | None = None):
        return self.outputs(features, self.grid, loads=loads)

    def tendons(self, features: torch.Tensor, fractions: torch.Tensor | None = None, ref=None, loads=None
                ) -> torch.Tensor:
        out = self.outputs(features, self.grid, ref, loads)
        return out if self.kind == "tendons" else out[2]

    @property
    def reference_grid(self) -> torch.Tensor:
        return self.grid


#: name -> (class, kind, config class, paper parameter count or None)
REGISTRY: dict[str, tuple[type[_OperatorBase], str, type, int | None]] = {
    "deeponet": (DeepONet, "tendons", DeepONetConfig, 219_904),
    "deeponet_pose": (DeepONet, "pose", DeepONetConfig, 205_668),
    "fno": (FNO, "tendons", FNOConfig, 168_844),
    "fno_pose": (FNO, "pose", FNOConfig, 168_457),
    # ours: the pose operators that also take gravity and a tip wrench (not in the paper)
    "deeponet_pose_loaded": (DeepONet, "pose", DeepONetConfig, None),
    "fno_pose_loaded": (FNO, "pose", FNOConfig, None),
}
#: Config defaults of registered models beyond their config class's.
_DEFAULTS: dict[str, dict] = {"deeponet_pose_loaded": {"loads": True, "reference": "linearized"},
                              "fno_pose_loaded": {"loads": True, "reference": "linearized"}}
#: The operators that take gravity and a tip wrench (``loads`` ``(B, 10)``), and those that do not.
LOADED = tuple(name for name in REGISTRY if _DEFAULTS.get(name, {}).get("loads"))
TENDON_ONLY = tuple(name for name in REGISTRY if name not in LOADED)


def build_model(name: str, hyperparameters: dict | None = None) -> _OperatorBase:
    """Instantiate a registered model; ``hyperparameters`` override its config's defaults."""
    if name not in REGISTRY:
        raise KeyError(f"unknown model {name!r}; known: {sorted(REGISTRY)}")
    cls, kind, config_cls, _ = REGISTRY[name]
    return cls(kind, config_cls(**(_DEFAULTS.get(name, {}) | (hyperparameters or {}))))


def hyperparameters(model: _OperatorBase) -> dict:
    return asdict(model.config)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
