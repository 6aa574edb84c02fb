"""Second derivatives of a multilayer perceptron by its structure.

A learned model's network is most often an ``nn.Sequential`` of ``nn.Linear`` layers and
elementwise activations. Differentiated twice by automatic differentiation, its Hessians
cost a double backward pass per output and input direction (``n (n + m)`` passes
through every layer). With ``a_l`` the pre-activations, ``J_l = da_l/dz`` their
Jacobians and ``g_il = dy_i/dh_l`` the sensitivity of output ``i`` to the activation
``h_l = s(a_l)``, the Hessian of output ``i`` is exactly

    ``d2 y_i / dz2 = sum_l J_l' diag(g_il * s''(a_l)) J_l``

(linear layers have no curvature): one forward pass of Jacobians, one backward pass of
sensitivities and a congruence per layer, all as matrix products over the batch.
:func:`mlp_taylor` computes the value, Jacobian and Hessians this way, and during the
Hessian pass of :func:`torchslq.dynamics.dynamics_hessians` / ``dynamics_vhp`` such a
network stands in by its second-order Taylor expansion (:func:`mlp_standin_hook`),
whatever model calls it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ._taylor import second_order_taylor

__all__ = ["mlp_taylor", "mlp_standin_hook", "takes_mlp_standin", "MAX_INPUT"]

#: networks with more inputs than this keep the autograd pass (the Hessians are
#: ``(rows, out, inputs, inputs)``)
MAX_INPUT = 16


def _tanh(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    d1 = 1.0 - h * h
    return d1, -2.0 * h * d1


def _sigmoid(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    d1 = h * (1.0 - h)
    return d1, d1 * (1.0 - 2.0 * h)


def _relu(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    return (a > 0).to(a.dtype), torch.zeros_like(a)


def _silu(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    s = torch.sigmoid(a)
    ds = s * (1.0 - s)
    return s + a * ds, ds * (2.0 + a * (1.0 - 2.0 * s))


def _identity(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    return torch.ones_like(a), torch.zeros_like(a)


# s' alone, for the Jacobian passes, where the pair computes s'' at extra cost
FIRST_ONLY = {
    _tanh: lambda a, h: 1.0 - h * h,
    _sigmoid: lambda a, h: h * (1.0 - h),
}

_INV_SQRT_2PI = 0.3989422804014327  # 1 / sqrt(2 pi)
_INV_SQRT_2 = 0.7071067811865476


def _gelu(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """GELU's ``a Phi(a)`` (the exact form): ``Phi + a phi`` and ``phi (2 - a^2)``."""
    pdf = _INV_SQRT_2PI * torch.exp(-0.5 * a * a)
    cdf = 0.5 * (1.0 + torch.erf(_INV_SQRT_2 * a))
    return cdf + a * pdf, pdf * (2.0 - a * a)


# elementwise functions a model applies to its features (graph_jacobian's table)
def _sin(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    return torch.cos(a), -h


def _cos(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    return -torch.sin(a), -h


def _exp(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    return h, h


def _power(p: float):
    """``(d1, d2)`` of ``a ** p`` for a number ``p`` (a zero coefficient gives zeros, not
    ``0 * a ** -1``, NaN at ``a = 0``)."""
    c1, c2 = p, p * (p - 1)

    def power(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
        d1 = c1 * a ** (p - 1) if c1 != 0 else torch.zeros_like(a)
        d2 = c2 * a ** (p - 2) if c2 != 0 else torch.zeros_like(a)
        return d1, d2

    return power


_square = _power(2)


def _activation(layer: nn.Module):
    """``(d1, d2)`` of an elementwise activation from its input ``a`` and output ``h``, or
    None for a layer this module does not know."""
    kind = type(layer)
    if kind is nn.Tanh:
        return _tanh
    if kind is nn.Sigmoid:
        return _sigmoid
    if kind is nn.ReLU:
        return _relu
    if kind is nn.SiLU:
        return _silu
    if kind is nn.Identity:
        return _identity
    if kind is nn.GELU and layer.approximate == "none":
        return _gelu
    if kind is nn.Softplus:
        beta, threshold = float(layer.beta), float(layer.threshold)

        def softplus(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
            s = torch.sigmoid(beta * a)
            linear = beta * a > threshold  # torch's softplus is the identity there
            d1 = torch.where(linear, 1.0, s)
            return d1, torch.where(linear, 0.0, beta * s * (1.0 - s))

        return softplus
    if kind is nn.ELU:
        alpha = float(layer.alpha)

        def elu(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
            neg = h + alpha
            return torch.where(a > 0, 1.0, neg), torch.where(a > 0, 0.0, neg)

        return elu
    if kind is nn.LeakyReLU:
        slope = float(layer.negative_slope)

        def leaky(a: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
            return torch.where(a > 0, 1.0, torch.full_like(a, slope)), torch.zeros_like(a)

        return leaky
    return None


def _layers(net: nn.Module) -> list | None:
    """``[("linear", layer, None) | ("act", layer, derivatives)]`` of a flat
    ``nn.Sequential`` of ``nn.Linear`` layers and known activations whose first layer is
    linear, else None."""
    if type(net) is not nn.Sequential or len(net) == 0 or type(net[0]) is not nn.Linear:
        return None
    out = []
    for layer in net:
        if type(layer) is nn.Linear:
            out.append(("linear", layer, None))
            continue
        fn = _activation(layer)
        if fn is None:
            return None
        out.append(("act", layer, fn))
    return out


def is_plain_mlp(net: nn.Module) -> bool:
    """Whether :func:`mlp_taylor` takes ``net`` (its input width aside)."""
    return _layers(net) is not None


def mlp_taylor(net: nn.Module, z: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
    """Value ``(rows, out)``, Jacobian ``(rows, out, k)`` and Hessians ``(rows, out, k,
    k)`` of a flat MLP (an ``nn.Sequential`` of ``nn.Linear`` and known elementwise
    activations) at the rows of ``z (rows, k)``, by the layered formula of the module
    docstring; None for another network or ``k > MAX_INPUT``. Detached."""
    layers = _layers(net)
    if layers is None or z.ndim != 2 or z.shape[1] > MAX_INPUT:
        return None
    rows, k = z.shape
    with torch.no_grad():
        h = z.detach()
        J = None  # (rows, k, width): d(current output)/dz, transposed; None: the identity
        sweep = []  # what the backward sweep of sensitivities needs, per layer
        for kind, layer, fn in layers:
            if kind == "linear":
                W = layer.weight.detach()
                h = torch.nn.functional.linear(h, W, layer.bias)
                if J is None:
                    J = W.T.unsqueeze(0).expand(rows, k, W.shape[0])
                else:  # one product over the batch: (rows k, w) @ (w, w')
                    J = (J.reshape(rows * k, J.shape[-1]) @ W.T).view(rows, k, W.shape[0])
                sweep.append((W, None, None))
            else:
                a = h
                h = layer(a)
                d1, d2 = fn(a, h)  # (rows, w)
                sweep.append((J, d1, d2))
                J = J * d1.unsqueeze(1)
        n_out = h.shape[1]
        # backward: G (n_out, rows, w) = d y / d(current output); H from every activation
        G = None  # None: the identity
        H = z.new_zeros(rows, k, k, n_out)
        for Ja, d1, d2 in reversed(sweep):
            if d1 is None:  # a linear layer, Ja its weight
                W = Ja
                if G is None:
                    G = W.unsqueeze(1).expand(n_out, rows, W.shape[1])
                else:
                    G = (G.reshape(n_out * rows, W.shape[0]) @ W).view(n_out, rows, -1)
                continue
            if G is None:  # the network ends in this activation
                G = torch.eye(n_out, dtype=z.dtype, device=z.device)
                G = G.unsqueeze(1).expand(n_out, rows, n_out)
            # sum_j (G_ij s''(a_j)) Ja_j' Ja_j, batched over rows: the outer products of
            # the columns of Ja (rows, k, k, w) against the weights (rows, w, n_out)
            c = (G * d2.unsqueeze(0)).permute(1, 2, 0)  # (rows, w, n_out)
            if Ja.stride(0) == 0:  # the first layer's: the same for every row
                outer = (Ja[0].unsqueeze(1) * Ja[0].unsqueeze(0)).view(k * k, -1)
                H += (outer @ c).view(rows, k, k, n_out)
            else:  # row a against rows b >= a (a (rows, k, k, w) tensor costs 3x more)
                for a in range(k):
                    Ha = torch.bmm(Ja[:, a : a + 1, :] * Ja[:, a:, :], c)  # (rows, k-a, n_out)
                    H[:, a, a:] += Ha
                    H[:, a + 1 :, a] += Ha[:, 1:]
            G = G * d1.unsqueeze(0)
        return h, J.transpose(1, 2), H.permute(0, 3, 1, 2)


def mlp_standin_hook(module: nn.Module, args: tuple, output: Tensor) -> Tensor | None:
    """A global forward hook (``torch.nn.modules.module.register_module_forward_hook``)
    for the Hessian pass: the output of a flat MLP whose input needs grad is replaced by
    its second-order Taylor expansion at that input (:func:`mlp_taylor`): the same value,
    first and second derivatives, for one structured pass instead of a double backward
    through every layer per output and direction. None (the output kept) otherwise."""
    if type(module) is not nn.Sequential or len(args) != 1:
        return None
    z = args[0]
    if not torch.is_tensor(z) or not z.requires_grad or z.ndim == 0:
        return None
    k = z.shape[-1]
    expansion = mlp_taylor(module, z.detach().reshape(-1, k))
    if expansion is None:
        return None
    value, J, H = expansion
    lead, n_out = z.shape[:-1], value.shape[-1]
    return value.reshape(*lead, n_out) + second_order_taylor(
        z - z.detach(), J.reshape(*lead, n_out, k), H.reshape(*lead, n_out, k, k)
    )


def takes_mlp_standin(module: nn.Module) -> bool:
    """Whether :func:`mlp_standin_hook` replaces ``module``'s output (given a small
    enough input that needs grad)."""
    return is_plain_mlp(module) and module[0].in_features <= MAX_INPUT
