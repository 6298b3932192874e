"""The MSE of a plain-MLP critic and its gradient, by a hand-written backward pass.

A CPU speed trick: TRPO's critic fit runs about a thousand tiny minibatch steps per update, and
there per-step overhead, not arithmetic, sets the speed. Autograd records and replays about twenty
small nodes per minibatch; for a critic of one known shape (``nn.Sequential`` of ``nn.Linear`` and
tanh/ReLU, as :func:`unipolicy_rl.networks.make_critic` builds) the backward pass is a few matrix
products. Any other critic takes autograd. ``tests/test_trpo.py`` checks that this path and
autograd's fit the same weights.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn


class PlainMLPRegression:
    """MSE loss and its gradient for a ``Linear -> act -> ... -> Linear`` critic, by hand.

    Autograd records and replays about twenty small nodes per minibatch; for a critic of this
    one known shape the backward pass is a few matrix products, written out below.
    """

    _ACTIVATIONS = (nn.Tanh, nn.ReLU)

    def __init__(self, linears: list[nn.Linear], activations: list[nn.Module]) -> None:
        self.linears = linears
        self.tanh = [isinstance(activation, nn.Tanh) for activation in activations]  # else ReLU
        self.params = [t for layer in linears for t in (layer.weight, layer.bias)]

    @classmethod
    def from_critic(cls, loss_module) -> PlainMLPRegression | None:
        """The fast path for ``loss_module``'s critic (a TRPO loss: ``critic_network``,
        ``critic_parameters()``, ``tensor_keys.value``), or ``None`` if it is not a plain MLP."""
        critic = loss_module.critic_network
        if not (
            isinstance(critic, TensorDictModule)
            and len(critic.in_keys) == 1
            and list(critic.out_keys) == [loss_module.tensor_keys.value]
            and isinstance(critic.module, nn.Sequential)
        ):
            return None
        layers = list(critic.module)
        linears, activations = layers[0::2], layers[1::2]
        if (
            len(layers) % 2 == 0
            or not all(type(layer) is nn.Linear and layer.bias is not None for layer in linears)
            or not all(type(act) in cls._ACTIVATIONS for act in activations)
        ):
            return None
        mlp = cls(linears, activations)
        critic_params = loss_module.critic_parameters()
        if {id(t) for t in mlp.params} != {id(t) for t in critic_params} or len(critic_params) != len(mlp.params):
            return None
        return mlp

    def loss_and_grads(
        self, inputs: torch.Tensor, target: torch.Tensor, coeff: float
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """``coeff * mean((mlp(inputs) - target)^2)`` and its gradient, in ``self.params`` order.

        Call under ``torch.no_grad()``: nothing here is recorded.
        """
        layer_inputs = [inputs]
        hidden = inputs
        for linear, is_tanh in zip(self.linears[:-1], self.tanh, strict=True):
            hidden = torch.addmm(linear.bias, hidden, linear.weight.t())
            hidden = hidden.tanh_() if is_tanh else hidden.relu_()
            layer_inputs.append(hidden)
        output_layer = self.linears[-1]
        error = torch.addmm(output_layer.bias, hidden, output_layer.weight.t())
        error = error.sub_(target.view_as(error))
        scale = coeff / error.numel()
        flat_error = error.view(-1)
        loss = torch.dot(flat_error, flat_error).mul_(scale)
        delta = error.mul_(2.0 * scale)  # d loss / d output
        grads: list[torch.Tensor] = [delta] * len(self.params)
        for index in range(len(self.linears) - 1, -1, -1):
            layer_input = layer_inputs[index]
            grads[2 * index] = delta.t() @ layer_input
            grads[2 * index + 1] = delta.sum(0)
            if index > 0:  # back through this linear map, then the activation that fed it
                delta = delta @ self.linears[index].weight
                if self.tanh[index - 1]:  # tanh' = 1 - tanh^2
                    delta = torch.addcmul(delta, delta * layer_input, layer_input, value=-1.0)
                else:
                    delta = delta.mul_(layer_input > 0)
        return loss, grads
