"""Pictures and a table of liver anatomies: the five meshes overlaid in one off-screen
render, and a Markdown table beside the paper's Table 2."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .anatomy import LIVERS, mesh_quality
from .mesh import TetMesh

COLOURS = ("#d95f02", "#1b9e77", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d")
WINDOW = (1600, 900)
VIEW = (0.35, -1.0, 0.55)  # camera direction from the anatomy
# a horizontal colour bar low in its panel, labelled at its two ends only (VTK sets the title in the labels' row,
# over any label in the middle), and a camera far enough (ZOOM) that the liver, turned to face its tools (wider
# from some sides), stays clear of it
SCALAR_BAR = dict(color="black", vertical=False, position_x=0.2, position_y=0.03, width=0.6, height=0.07, n_labels=2)
ZOOM = 0.9


def render_anatomies(meshes: dict[str, TetMesh], out_png) -> None:
    """Off-screen PNG: the anatomies overlaid on top (each surface in its own
    semi-transparent colour, its fixed (Dirichlet) nodes as points of the same colour, with
    a legend) and each one alone, opaque with its mesh edges, in a row below."""
    import pyvista as pv

    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    n = max(len(meshes), 1)
    plotter = pv.Plotter(off_screen=True, window_size=WINDOW, shape=(3, n),
                         groups=[(np.s_[:2], np.s_[:])], border=False)
    plotter.set_background("white")
    colours = [COLOURS[i % len(COLOURS)] for i in range(len(meshes))]
    centre = np.mean([m.nodes.mean(axis=0) for m in meshes.values()], axis=0)
    for i, ((name, mesh), colour) in enumerate(zip(meshes.items(), colours)):
        surface = pv.PolyData.from_regular_faces(mesh.nodes, mesh.boundary_faces())
        plotter.subplot(0, 0)
        plotter.add_mesh(surface, color=colour, opacity=0.25, smooth_shading=True, label=name,
                         silhouette=dict(color=colour, line_width=3))
        plotter.add_points(mesh.nodes[mesh.fixed], color=colour, point_size=6, render_points_as_spheres=True)
        plotter.subplot(2, i)
        plotter.add_mesh(surface, color=colour, show_edges=True, edge_color="#444444", line_width=0.5)
        plotter.add_points(mesh.nodes[mesh.fixed], color="black", point_size=3, render_points_as_spheres=True)
        plotter.add_text(name, font_size=10, color="black")
        _view(plotter, centre, zoom=1.15)
    plotter.subplot(0, 0)
    plotter.add_legend(bcolor="white", face="rectangle", size=(0.08, 0.22), loc="upper right")
    plotter.add_text("liver anatomies overlaid (points: fixed nodes of the flat visceral face)",
                     font_size=12, color="black")
    plotter.add_axes(color="black")
    _view(plotter, centre, zoom=1.5)
    _screenshot(plotter, out_png)


def _screenshot(plotter, out_png: Path) -> None:
    """Write to a temporary name first so a failed render never leaves half a PNG behind."""
    tmp = out_png.with_name(out_png.stem + ".tmp" + out_png.suffix)
    plotter.screenshot(str(tmp))
    plotter.close()
    os.replace(tmp, out_png)


def _view(plotter, centre, zoom: float, towards=None) -> None:
    """Anterior-superior view (patient's right lobe on the left, like an anatomy atlas),
    high enough to see the dome, low enough to see the flat base. With ``towards`` (a point,
    e.g. the tools' mean), turned about the vertical axis to face it: a tool on the far side
    would otherwise hide the stress it makes."""
    view = np.array(VIEW, dtype=np.float64)
    if towards is not None:
        side = (np.asarray(towards, dtype=np.float64) - centre)[:2]
        if np.linalg.norm(side) > 0:
            view[:2] = np.linalg.norm(view[:2]) * side / np.linalg.norm(side)
    plotter.camera.focal_point = centre
    plotter.camera.position = centre + 0.5 * view
    plotter.camera.up = (0.0, 0.0, 1.0)
    plotter.reset_camera()
    plotter.camera.zoom(zoom)


def anatomy_table(meshes: dict[str, TetMesh]) -> str:
    """Markdown table of the meshes beside the paper's Table 2 values (where the name is one
    of ``LIVERS``)."""
    rows = ["| anatomy | volume [m^3] | nodes | tets | fixed nodes | min dihedral [deg] "
            "| min altitude / mean edge | paper volume [m^3] | paper nodes | paper tets |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name, mesh in meshes.items():
        q = mesh_quality(mesh)
        spec = LIVERS.get(name)
        paper = (f"{spec.volume:.2e} | {spec.nodes} | {spec.tets}" if spec else "- | - | -")
        rows.append(f"| {name} | {mesh.volume:.3e} | {len(mesh.nodes)} | {len(mesh.tets)} | "
                    f"{int(np.count_nonzero(mesh.fixed))} | {q['min_dihedral_deg']:.1f} | "
                    f"{q['min_altitude_over_mean_edge']:.3f} | {paper} |")
    return "\n".join(rows) + "\n"


def render_simulation(mesh: TetMesh, sim: dict, out_png, title: str = "") -> None:
    """Off-screen PNG of one ground-truth simulation (a ``dataset.read_simulation`` record):
    the deformed surface at the end of the ramp (the first snapshot at or past half the simulated
    time) and at the last snapshot, coloured by the displacement magnitude [mm] and by the von
    Mises stress [kPa], over the rest shape (grey wireframe), with the tools' loaded nodes as red spheres."""
    import pyvista as pv

    q, sigma = sim["q"], sim["sigma"].astype(np.float64)
    steps = len(q) // 2, len(q) - 1
    xx, yy, zz, xy, yz, xz = sigma.transpose(2, 0, 1)
    von_mises = np.sqrt(0.5 * ((xx - yy) ** 2 + (yy - zz) ** 2 + (zz - xx) ** 2) + 3 * (xy**2 + yz**2 + xz**2))
    fields = (("|u| [mm]", 1e3 * np.linalg.norm(q - mesh.nodes[None], axis=-1)), ("von Mises [kPa]", 1e-3 * von_mises))
    faces = mesh.boundary_faces()
    rest = pv.PolyData.from_regular_faces(mesh.nodes, faces)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    plotter = pv.Plotter(off_screen=True, window_size=WINDOW, shape=(2, 2), border=False)
    plotter.set_background("white")
    centre = mesh.nodes.mean(axis=0)
    for row, (label, values) in enumerate(fields):
        limits = (0.0, float(np.percentile(values[list(steps)], 99.5)) or 1.0)
        for col, s in enumerate(steps):
            plotter.subplot(row, col)
            surface = pv.PolyData.from_regular_faces(q[s].astype(np.float64), faces)
            surface.point_data[label] = values[s]
            plotter.add_mesh(rest, style="wireframe", color="#bbbbbb", line_width=0.5)
            plotter.add_mesh(surface, scalars=label, cmap="viridis", clim=limits, smooth_shading=True,
                             scalar_bar_args=dict(SCALAR_BAR, title=label))
            plotter.add_points(q[s][sim["loaded"]].astype(np.float64), color="red", point_size=14,
                               render_points_as_spheres=True)
            plotter.add_text(f"{title}  snapshot {s}", font_size=10, color="black")
            _view(plotter, centre, zoom=ZOOM, towards=q[-1][sim["loaded"]].mean(axis=0))
    _screenshot(plotter, out_png)


def render_comparison(mesh: TetMesh, ref: np.ndarray, pred: np.ndarray, loaded, out_png, title: str = "") -> None:
    """Off-screen PNG of a rollout's final step: the FEM (left) beside the network (right),
    coloured by |u| [mm] (top) and by sigma_xy [kPa] (bottom), on shared colour scales;
    ``ref``/``pred`` are (S+1, N, 12) states."""
    import pyvista as pv

    faces = mesh.boundary_faces()
    rest = pv.PolyData.from_regular_faces(mesh.nodes, faces)
    last = {"FEM": ref[-1].astype(np.float64), "network": pred[-1].astype(np.float64)}
    fields = (("|u| [mm]", lambda z: 1e3 * np.linalg.norm(z[:, :3] - mesh.nodes, axis=1), "viridis"),
              ("sigma_xy [kPa]", lambda z: 1e-3 * z[:, 9], "coolwarm"))
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    plotter = pv.Plotter(off_screen=True, window_size=WINDOW, shape=(2, 2), border=False)
    plotter.set_background("white")
    for row, (label, value, cmap) in enumerate(fields):
        ref_values = value(last["FEM"])
        hi = float(np.percentile(np.abs(ref_values), 99.5)) or 1.0
        limits = (0.0, hi) if row == 0 else (-hi, hi)
        for col, (name, z) in enumerate(last.items()):
            plotter.subplot(row, col)
            surface = pv.PolyData.from_regular_faces(z[:, :3], faces)
            surface.point_data[label] = value(z)
            plotter.add_mesh(rest, style="wireframe", color="#bbbbbb", line_width=0.5)
            plotter.add_mesh(surface, scalars=label, cmap=cmap, clim=limits, smooth_shading=True,
                             scalar_bar_args=dict(SCALAR_BAR, title=label))
            plotter.add_points(z[loaded, :3], color="red", point_size=14, render_points_as_spheres=True)
            plotter.add_text(f"{name}  {title}  final step", font_size=10, color="black")
            _view(plotter, mesh.nodes.mean(axis=0), zoom=ZOOM, towards=last["FEM"][loaded, :3].mean(axis=0))
    _screenshot(plotter, out_png)
