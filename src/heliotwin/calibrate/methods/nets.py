"""Small per-heliostat networks, batched: one independent MLP per heliostat, evaluated for all records at once.

Weights have a leading heliostat axis ``[H, ...]``; a record uses its heliostat's weights (gathered by
``heliostat_index``). Self-normalising (SELU + LeCun-normal initialisation) as in the hybrid-kinematics
and MLP papers. Every random draw takes a ``torch.Generator``.
"""
from __future__ import annotations

import math

import torch


class BatchedMLP(torch.nn.Module):
    """H independent MLPs ``in -> hidden x depth (SELU) -> out``.

    Parameters
    ----------
    heliostats : int
    n_in, n_out : int
    hidden : int
        Neurons per hidden layer.
    depth : int
        Hidden layers.
    generator : torch.Generator
        Seeds the initialisation.
    zero_output : bool
        Start with a zero output layer (the network's first prediction is exactly 0: a hybrid starts at
        its pre-aligned rigid body).
    """

    def __init__(self, heliostats: int, n_in: int, n_out: int, hidden: int, depth: int,
                 generator: torch.Generator, zero_output: bool = False, dtype=torch.float64):
        super().__init__()
        sizes = [n_in] + [hidden] * depth + [n_out]
        self.weights = torch.nn.ParameterList()
        self.biases = torch.nn.ParameterList()
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
            w = torch.randn(heliostats, a, b, generator=generator, dtype=dtype) / math.sqrt(a)  # LeCun normal
            if zero_output and i == len(sizes) - 2:
                w = torch.zeros_like(w)
            self.weights.append(torch.nn.Parameter(w))
            self.biases.append(torch.nn.Parameter(torch.zeros(heliostats, b, dtype=dtype)))
        self.config = {"n_in": n_in, "n_out": n_out, "hidden": hidden, "depth": depth}

    def forward(self, x: torch.Tensor, heliostat_index: torch.Tensor) -> torch.Tensor:
        """``x`` [R, n_in], ``heliostat_index`` [R] -> [R, n_out]."""
        n = len(self.weights)
        out = x.new_zeros(len(x), self.config["n_out"])
        # Loop over heliostats (tens) rather than gathering a weight matrix per record (thousands):
        # the gather costs R x in x out memory traffic per layer and dominates training time.
        for hh in torch.unique(heliostat_index).tolist():
            m = heliostat_index == hh
            h = x[m]
            for i, (w, b) in enumerate(zip(self.weights, self.biases)):
                h = h @ w[hh] + b[hh]
                if i < n - 1:
                    h = torch.nn.functional.selu(h)
            out = out.index_put((m.nonzero().flatten(),), h)
        return out

    def dense(self, x: torch.Tensor) -> torch.Tensor:
        """All networks at once on a padded batch: ``x`` [H, N, n_in] (row h through network h) -> [H, N, n_out].

        One batched matrix product per layer (no loop over heliostats): the pretraining's thousands of
        samples per network are padded to the same N by the caller.
        """
        n = len(self.weights)
        h = x
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b.unsqueeze(1), h, w)
            if i < n - 1:
                h = torch.nn.functional.selu(h)
        return h

    def weight_norm(self) -> torch.Tensor:
        """Sum of squared weights per heliostat [H] (for weight decay)."""
        return sum((w ** 2).flatten(1).sum(1) for w in self.weights)

    def state_of(self, h: int) -> dict:
        """One heliostat's weights as a flat dict of tensors (for the calibration file): ``w{i}`` of shape
        (n_in_i, n_out_i) and ``b{i}`` of shape (n_out_i,) per layer i."""
        out = {}
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            out[f"w{i}"] = w[h].detach().clone()
            out[f"b{i}"] = b[h].detach().clone()
        return out

    @classmethod
    def from_state(cls, config: dict, state: dict) -> "BatchedMLP":
        """A 1-heliostat network from :meth:`state_of` output."""
        net = cls(1, config["n_in"], config["n_out"], config["hidden"], config["depth"],
                  torch.Generator().manual_seed(0))
        with torch.no_grad():
            for i in range(len(net.weights)):
                net.weights[i].copy_(torch.as_tensor(state[f"w{i}"]).double().unsqueeze(0))
                net.biases[i].copy_(torch.as_tensor(state[f"b{i}"]).double().unsqueeze(0))
        return net

    @classmethod
    def from_states(cls, config: dict, states: list) -> "BatchedMLP":
        """A len(states)-network batch from :meth:`state_of` outputs (e.g. one network per motor axis)."""
        net = cls(len(states), config["n_in"], config["n_out"], config["hidden"], config["depth"],
                  torch.Generator().manual_seed(0))
        with torch.no_grad():
            for i in range(len(net.weights)):
                net.weights[i].copy_(torch.stack([torch.as_tensor(s[f"w{i}"]).double() for s in states]))
                net.biases[i].copy_(torch.stack([torch.as_tensor(s[f"b{i}"]).double() for s in states]))
        return net

    def copy_rows(self, other: "BatchedMLP", rows: torch.Tensor) -> None:
        """Copy the weights of heliostats ``rows`` (bool [H]) from ``other`` (same shapes)."""
        with torch.no_grad():
            for a, b in zip(list(self.weights) + list(self.biases), list(other.weights) + list(other.biases)):
                a[rows] = b[rows]
