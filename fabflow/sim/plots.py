"""PNG plots of a Monte Carlo study (matplotlib, Agg backend, no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from fabflow.sim.monte_carlo import StudyResult
from fabflow.sim.run import Study


def plot_histogram(study: Study, result: StudyResult, path: Path) -> Path:
    """Histogram of the translational deviation of every element in every run (mm)."""
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    values = 1000 * result.translation_m.ravel()
    tol = 1000 * study.project.tolerances.position
    if values.size:
        ax.hist(values, bins=60, color="#4477aa", edgecolor="white", linewidth=0.3)
        ax.axvline(np.percentile(values, 95), color="#cc6677", ls="--", label="p95")
    ax.axvline(tol, color="black", lw=1.5, label=f"tolerance {tol:g} mm")
    ax.set_xlabel("as-built deviation of element origin (mm)")
    ax.set_ylabel("element placements")
    ax.set_title(
        f"{study.project.name}: {result.method}, "
        f"{result.runs.size} runs x {study.n_elements} elements"
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_heat_map(study: Study, result: StudyResult, path: Path) -> Path:
    """Plan view of the elements coloured by their mean deviation (mm); higher ones on top."""
    fig, ax = plt.subplots(figsize=(7, 6), dpi=110)
    xyz = study.T_world_element[:, :3, 3]
    mean = 1000 * result.translation_m.mean(axis=0) if result.runs.size else np.zeros(len(xyz))
    order = np.argsort(xyz[:, 2], kind="stable")
    sc = ax.scatter(
        xyz[order, 0], xyz[order, 1], c=mean[order], cmap="viridis", s=18, edgecolors="none"
    )
    fig.colorbar(sc, ax=ax, label="mean deviation (mm)")
    labels: dict[tuple[float, float], list[str]] = {}
    for station in study.stations:
        xy = tuple(np.round(station.T_world_platform[:2, 3], 3))
        ids = labels.setdefault(xy, [])
        if station.id not in ids:
            ids.append(station.id)
    for (x, y), ids in labels.items():
        ax.plot(x, y, marker="s", color="#cc6677", ms=7)
        ax.annotate("/".join(ids), (x, y), textcoords="offset points", xytext=(6, 4))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"mean as-built deviation per element ({result.method}; squares: stations)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_localization(study: Study, result: StudyResult, path: Path) -> Path:
    """Horizontal localization error per station (box plot) with the predicted sigma."""
    ids = list(dict.fromkeys(s.id for s in study.stations))
    visit_station = np.array([s.id for s in study.stations])
    data, predicted = [], []
    for sid in ids:
        cols = np.flatnonzero(visit_station == sid)
        e = result.localization_error[:, cols, :2].reshape(-1, 2)
        c = result.localization_covariance[:, cols]
        data.append(1000 * np.linalg.norm(e, axis=1))
        trace = c[..., 0, 0] + c[..., 1, 1]
        predicted.append(1000 * float(np.sqrt(np.mean(trace))) if trace.size else np.nan)
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    ax.boxplot(data, showfliers=True)
    ax.set_xticks(range(1, len(ids) + 1), ids)
    ax.plot(range(1, len(ids) + 1), predicted, "D", color="#cc6677", label="predicted sigma (xy)")
    ax.set_xlabel("station")
    ax.set_ylabel("horizontal base error (mm)")
    ax.set_title(f"localization error per station ({result.method})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_plots(study: Study, result: StudyResult, folder: Path) -> list[Path]:
    """All three plots of a study into ``folder``."""
    return [
        plot_histogram(study, result, folder / "deviation_histogram.png"),
        plot_heat_map(study, result, folder / "deviation_heat_map.png"),
        plot_localization(study, result, folder / "localization_error.png"),
    ]
