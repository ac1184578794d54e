"""Pictures: bird's-eye-view flow images (paper Figure 1 style), speed histograms and study plots, as PNG."""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors as mcolors  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def flow_colors(flow_mps: np.ndarray, max_speed_mps: float = 8.0) -> np.ndarray:
    """RGB [N,3]: hue = direction of motion in x-y, brightness = speed (stationary points dim grey)."""
    speed = np.linalg.norm(flow_mps[:, :2], axis=1)
    hue = (np.arctan2(flow_mps[:, 1], flow_mps[:, 0]) + np.pi) / (2 * np.pi)
    value = np.clip(speed / max_speed_mps, 0.0, 1.0)
    hsv = np.stack([hue, np.ones_like(hue), 0.35 + 0.65 * value], -1)
    rgb = mcolors.hsv_to_rgb(hsv)
    still = speed < 0.25
    rgb[still] = 0.35
    return rgb


def bev_flow_png(path: str, points_xyz: np.ndarray, flows: dict[str, np.ndarray], extent_m: float = 40.0,
                 title: str = "") -> str:
    """Side-by-side BEV panels (e.g. {"prediction": ..., "ground truth": ...}) of points coloured by flow."""
    fig, axes = plt.subplots(1, len(flows), figsize=(7 * len(flows), 7), squeeze=False)
    near = (np.abs(points_xyz[:, 0]) < extent_m) & (np.abs(points_xyz[:, 1]) < extent_m)
    for ax, (name, flow) in zip(axes[0], flows.items()):
        c = flow_colors(flow[near])
        order = np.argsort(np.linalg.norm(flow[near][:, :2], axis=1))  # moving points on top
        ax.scatter(points_xyz[near][order, 0], points_xyz[near][order, 1], c=c[order], s=0.3, linewidths=0)
        ax.set_facecolor("black")
        ax.set_aspect("equal")
        ax.set_xlim(-extent_m, extent_m)
        ax.set_ylim(-extent_m, extent_m)
        ax.set_title(name)
        ax.set_xlabel("x (m, vehicle frame)")
        ax.set_ylabel("y (m)")
    # Direction legend: a colour wheel.
    wheel = fig.add_axes([0.005, 0.02, 0.08, 0.08], projection="polar")
    theta = np.linspace(-np.pi, np.pi, 64)
    wheel.scatter(theta, np.ones_like(theta), c=flow_colors(np.stack([np.cos(theta), np.sin(theta), 0 * theta], -1)
                                                           * 8.0), s=12)
    wheel.set_axis_off()
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def speed_histogram_png(path: str, speeds_by_class: dict[str, np.ndarray], title: str = "") -> str:
    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.linspace(0.0, 15.0, 61)
    for name, speeds in speeds_by_class.items():
        if len(speeds):
            ax.hist(speeds, bins=bins, histtype="step", density=True, label=f"{name} (n={len(speeds)})")
    ax.set_xlabel("speed of moving points (m/s)")
    ax.set_ylabel("density")
    ax.legend()
    if title:
        ax.set_title(title)
    return _save(fig, path)


def lines_png(path: str, panels: dict[str, dict[str, tuple[list, list]]], x_label: str, title: str = "",
              log_x: bool = True, y_range=(0.0, 1.0)) -> str:
    """One panel per key (its y label), one line per series {name: (xs, ys)}: e.g. accuracy vs data share."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.6), squeeze=False)
    for ax, (y_label, series) in zip(axes[0], panels.items()):
        for name, (xs, ys) in series.items():
            ax.plot(xs, ys, "o-", label=name)
        if log_x:
            ax.set_xscale("log")
        ax.set_xlabel(x_label)
        ax.set_ylabel(y_label)
        if y_range is not None:
            ax.set_ylim(*y_range)
        ax.grid(alpha=0.3)
    axes[0, 0].legend()
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def grouped_bars_png(path: str, groups: list[str], series: dict[str, list[float]], y_label: str,
                     title: str = "") -> str:
    """Bars of each series (e.g. a model variant) side by side over the groups (e.g. metrics)."""
    fig, ax = plt.subplots(figsize=(max(6.0, 0.5 * len(groups) * len(series) + 3), 3.8))
    width = 0.8 / max(len(series), 1)
    for i, (name, values) in enumerate(series.items()):
        ax.bar(np.arange(len(groups)) + i * width, values, width, label=name)
    ax.set_xticks(np.arange(len(groups)) + 0.4 - width / 2)
    ax.set_xticklabels(groups, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(y_label)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def _save(fig, path: str) -> str:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
