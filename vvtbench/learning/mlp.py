"""A small multilayer perceptron in numpy: fitted by Adam, stored as plain arrays.

The ``learned`` solver's per-voxel model. Weights are arrays (``W0, b0, W1, b1, ...`` and the
input standardization), so a weights file loads with ``allow_pickle=False`` and the model is
evaluated by :func:`mlp_predict` alone. Every random draw (initialization, minibatch order)
comes from the ``seed`` argument.
"""

from __future__ import annotations

import numpy as np


def _layers(params: dict) -> int:
    return sum(1 for k in params if k.startswith("W"))


def mlp_forward(params: dict, Z: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Output (n,) of standardized inputs ``Z`` and the hidden activations (ReLU)."""
    hidden = []
    h = Z
    n = _layers(params)
    for i in range(n):
        h = h @ params[f"W{i}"] + params[f"b{i}"]
        if i < n - 1:
            h = np.maximum(h, 0.0)
            hidden.append(h)
    return h[:, 0], hidden


def mlp_predict(params: dict, X: np.ndarray) -> np.ndarray:
    """Prediction (n,) for raw inputs ``X`` (n, n_features)."""
    Z = (np.asarray(X, dtype=float) - params["x_mean"]) / params["x_std"]
    return mlp_forward(params, Z)[0] * float(params["y_std"]) + float(params["y_mean"])


CHUNK = 1 << 18  # rows standardized at a time: memory of a float64 copy of X never needed


def column_moments(X: np.ndarray, chunk: int = CHUNK) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of each column of ``X``, accumulated over row chunks in
    float64 (no copy of ``X`` is made).

    >>> X = np.arange(12.0).reshape(6, 2)
    >>> [np.allclose(a, b) for a, b in zip(column_moments(X, chunk=4), (X.mean(0), X.std(0)))]
    [True, True]
    """
    n = len(X)
    mean = np.zeros(X.shape[1])
    for a in range(0, n, chunk):
        mean += X[a:a + chunk].sum(axis=0, dtype=np.float64)
    mean /= n
    var = np.zeros(X.shape[1])
    for a in range(0, n, chunk):
        var += ((X[a:a + chunk] - mean) ** 2).sum(axis=0)
    return mean, np.sqrt(var / n)


def standardize(X: np.ndarray, mean: np.ndarray, std: np.ndarray, chunk: int = CHUNK
                ) -> np.ndarray:
    """``(X - mean) / std`` as float32, computed a chunk of rows at a time."""
    Z = np.empty(X.shape, dtype=np.float32)
    for a in range(0, len(X), chunk):
        Z[a:a + chunk] = (X[a:a + chunk] - mean) / std
    return Z


def fit_mlp(X: np.ndarray, y: np.ndarray, hidden: tuple[int, ...] = (64, 32),
            epochs: int = 20, batch: int = 2048, lr: float = 2e-3, weight_decay: float = 1e-5,
            seed: int = 0, sample_weight: np.ndarray | None = None,
            steps: int | None = None) -> dict:
    """Least-squares fit of an MLP (ReLU hidden layers, linear output) by Adam.

    Parameters
    ----------
    X : (n, n_features) inputs; standardized inside (their mean and spread are stored).
    y : (n,) targets; standardized inside.
    hidden : widths of the hidden layers.
    epochs, batch, lr : passes over the data, minibatch size, Adam step (cosine-decayed).
    steps : Adam steps in all, if given, instead of ``epochs`` full passes (the last pass
        is cut short; each pass draws a new minibatch order).
    weight_decay : L2 penalty on the weight matrices.
    seed : seeds the initialization (He) and the minibatch order.
    sample_weight : (n,) optional per-sample weights of the squared error.

    Returns
    -------
    dict of arrays: ``W0, b0, ...``, ``x_mean``, ``x_std``, ``y_mean``, ``y_std``.

    Memory: ``X`` and one float32 copy of it (standardized in chunks of rows).
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    if X.ndim != 2 or len(X) != len(y) or len(X) == 0:
        raise ValueError(f"fit_mlp: X (n, f) and y (n,) of one length, got {X.shape}, {y.shape}")
    if steps is not None and steps < 1:
        raise ValueError(f"fit_mlp: steps must be >= 1, got {steps}")
    rng = np.random.default_rng(seed)
    x_mean, x_std = column_moments(X)
    x_std[x_std == 0] = 1.0
    y_mean, y_std = float(y.mean()), float(y.std()) or 1.0
    Z = standardize(X, x_mean, x_std)
    t = ((y - y_mean) / y_std).astype(np.float32)
    sw = (np.ones(len(y)) if sample_weight is None else np.asarray(sample_weight, float))
    sw = (sw / sw.mean()).astype(np.float32)
    sizes = [Z.shape[1], *hidden, 1]
    params = {}
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        params[f"W{i}"] = (rng.standard_normal((a, b)) * np.sqrt(2.0 / a)).astype(np.float32)
        params[f"b{i}"] = np.zeros(b, np.float32)
    m = {k: np.zeros_like(v) for k, v in params.items()}
    s = {k: np.zeros_like(v) for k, v in params.items()}
    b1, b2, eps = 0.9, 0.999, 1e-8
    n_layers = len(sizes) - 1
    steps_per_epoch = max(1, int(np.ceil(len(Z) / batch)))
    total = int(steps) if steps is not None else epochs * steps_per_epoch
    step = 0
    while step < total:
        order = rng.permutation(len(Z))
        for k in range(min(steps_per_epoch, total - step)):
            idx = order[k * batch:(k + 1) * batch]
            zb, tb, wb = Z[idx], t[idx], sw[idx]
            out, hidden_act = mlp_forward(params, zb)
            grad_out = (2.0 / len(idx)) * (wb * (out - tb))[:, None]
            acts = [zb, *hidden_act]
            grads = {}
            g = grad_out
            for i in range(n_layers - 1, -1, -1):
                grads[f"W{i}"] = acts[i].T @ g + weight_decay * params[f"W{i}"]
                grads[f"b{i}"] = g.sum(axis=0)
                if i > 0:
                    g = (g @ params[f"W{i}"].T) * (acts[i] > 0)
            step += 1
            rate = lr * 0.5 * (1.0 + np.cos(np.pi * (step - 1) / total))
            for key, grad in grads.items():
                m[key] = b1 * m[key] + (1 - b1) * grad
                s[key] = b2 * s[key] + (1 - b2) * grad * grad
                mhat = m[key] / (1 - b1**step)
                shat = s[key] / (1 - b2**step)
                params[key] = params[key] - rate * mhat / (np.sqrt(shat) + eps)
    out = {k: v.astype(np.float64) for k, v in params.items()}
    out.update(x_mean=x_mean, x_std=x_std, y_mean=np.float64(y_mean), y_std=np.float64(y_std))
    return out
