"""Named scenes for the simulator: the calibration target, reference boards and scan scenes.

World frame = target frame (mm): X right, Y up, Z towards the rig. The default rig sits at
Z = 1000 and looks towards -Z, so an object at Z = 0 is about 1 m away.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from multislit.errors import MultislitError
from multislit.sim.primitives import (
    F64,
    Box,
    HeightField,
    Polygon,
    Primitive,
    Scene,
    Sphere,
    albedo_steps,
    checker_markers,
    constant,
    noise_texture,
)


def backdrop_wall(z: float, albedo: float = 0.5, name: str = "wall") -> Polygon:
    """An unbounded fronto-parallel wall at world Z = ``z`` mm (list its name in ``Scene.backdrop``)."""
    return Polygon((0, 0, z), (0, 0, 1), texture=constant(albedo), name=name)


def reference_board(distance: float, rig_z: float = 1000.0) -> Scene:
    """The plain flat reference board, fronto-parallel, ``distance`` mm from the rig."""
    board = Polygon(
        (0, 0, rig_z - distance),
        (0, 0, 1),
        outline=np.array([[-900, -800], [900, -800], [900, 800], [-900, 800]], float),
        texture=constant(0.8),
        name="board",
    )
    return Scene(
        f"reference_{distance:.0f}", [board], {"plane": board.plane.tolist()}, backdrop=("board",)
    )


@dataclass(frozen=True)
class TargetDesign:
    """The standard object: a concave corner of three flat faces carrying checker markers.

    Two vertical walls at +-45 degrees about the vertical meet at the corner; below them a steep
    ramp (``ramp_slope`` = dY/dZ... its normal is (0, ramp_slope, 1)) closes the corner, so the
    vertical slit planes cross all three faces nearly along v. Markers lie on a grid over each
    face so that they span the image (lens distortion is then well determined).
    """

    depth: float = 210.0  # mm, how far the walls reach from the corner towards the rig
    height: float = 250.0  # mm, height of the walls above the corner
    ramp_depth: float = 200.0  # mm, how far the ramp reaches towards the rig
    ramp_slope: float = 1.0  # the ramp drops 1 / ramp_slope mm per mm towards the rig
    marker_size: float = 26.0
    marker_pitch: float = 64.0
    corner_z: float = -60.0  # world Z of the corner (the deepest point)


def _grid_markers(prim: Polygon, outline: F64, design: TargetDesign) -> F64:
    """Marker centres (local a, b) on a grid over a face, each square well inside the face."""
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    pitch = design.marker_pitch
    na = int((hi[0] - lo[0]) // pitch)
    nb = int((hi[1] - lo[1]) // pitch)
    ga = lo[0] + (hi[0] - lo[0] - (na - 1) * pitch) / 2 + pitch * np.arange(max(na, 1))
    gb = lo[1] + (hi[1] - lo[1] - (nb - 1) * pitch) / 2 + pitch * np.arange(max(nb, 1))
    A, B = np.meshgrid(ga, gb)
    cand = np.stack([A.ravel(), B.ravel()], axis=1)
    m = 0.75 * design.marker_size
    ok = np.ones(len(cand), bool)
    for da, db in ((-m, -m), (m, -m), (m, m), (-m, m)):
        ok &= prim.contains(cand[:, 0] + da, cand[:, 1] + db)
    return cand[ok]


def standard_object(design: TargetDesign = TargetDesign()) -> tuple[Scene, list[dict], list[dict]]:
    """Build the calibration target (world frame = target frame: the corner at (0, 0, corner_z)).

    Returns
    -------
    scene, markers (dicts with id and xyz), faces (dicts with id, plane, polygon)
    """
    D, H, R, sl, z0 = (
        design.depth,
        design.height,
        design.ramp_depth,
        design.ramp_slope,
        design.corner_z,
    )
    c = np.array([0.0, 0.0, z0])
    yb = -R / sl  # the ramp's front edge height
    walls = {
        # corner, top, top front, bottom front, ramp front corner
        "F1": np.array([[0, 0, 0], [0, H, 0], [-D, H, D], [-D, yb, D], [-R, yb, R]], float),
        "F2": np.array([[0, 0, 0], [0, H, 0], [D, H, D], [D, yb, D], [R, yb, R]], float),
    }
    ramp = np.array([[0, 0, 0], [-R, yb, R], [R, yb, R]], float)
    faces_def = [
        ("F1", np.array([1.0, 0.0, 1.0]), walls["F1"]),
        ("F2", np.array([-1.0, 0.0, 1.0]), walls["F2"]),
        ("F3", np.array([0.0, sl, 1.0]), ramp),
    ]
    prims: list[Primitive] = []
    markers: list[dict] = []
    faces: list[dict] = []
    k = 0
    for fid, normal, poly in faces_def:
        poly_world = c + poly
        n = normal / np.linalg.norm(normal)
        tmp = Polygon(c, n)
        a_w, b_w = tmp.local(poly_world)
        outline = np.stack([a_w, b_w], axis=1)
        shape = Polygon(c, n, outline=outline)
        grid = _grid_markers(shape, outline, design)
        prim = Polygon(
            c,
            n,
            outline=outline,
            texture=checker_markers(grid, design.marker_size),
            name=f"target_{fid}",
        )
        prims.append(prim)
        for g in grid:
            k += 1
            markers.append({"id": f"M{k:02d}", "xyz": prim.to_world(g[0], g[1]).round(6).tolist()})
        faces.append({"id": fid, "plane": prim.plane.tolist(), "polygon": poly_world.tolist()})
    prims.append(backdrop_wall(z0 - 400.0, 0.3, "background"))
    return Scene("target", prims, {}, backdrop=("background",)), markers, faces


def holes_board(tilt_deg: float = 0.0, distance: float = 900.0, rig_z: float = 1000.0) -> Scene:
    """The paper's Table 1 plate: holes of 100, 50 and 30 mm in a board, a far wall behind."""
    z = rig_z - distance
    tilt = np.radians(tilt_deg)
    normal = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    holes = np.array([[-95.0, 20.0, 50.0], [40.0, 20.0, 25.0], [120.0, 20.0, 15.0]])
    board = Polygon(
        (0, 0, z),
        normal,
        outline=np.array([[-300, -250], [300, -250], [300, 250], [-300, 250]], float),
        holes=holes,
        texture=constant(0.8),
        name="plate",
    )
    wall = backdrop_wall(z - 400.0, 0.6)
    info = {
        "plane": board.plane.tolist(),
        "holes": [
            {"centre": board.to_world(h[0], h[1]).tolist(), "diameter": 2 * h[2]} for h in holes
        ],
    }
    name = "holes" if tilt_deg == 0 else f"holes_tilt{tilt_deg:.0f}"
    return Scene(name, [board, wall], info, backdrop=("wall",))


def spheres(rig_z: float = 1000.0) -> Scene:
    c = [
        (-120.0, 40.0, rig_z - 880.0, 60.0),
        (60.0, -60.0, rig_z - 930.0, 45.0),
        (130.0, 90.0, rig_z - 850.0, 35.0),
    ]
    prims: list[Primitive] = [Sphere(x[:3], x[3], name=f"sphere{i}") for i, x in enumerate(c)]
    prims.append(backdrop_wall(rig_z - 1150.0, 0.55))
    return Scene(
        "spheres",
        prims,
        {"spheres": [{"centre": list(x[:3]), "radius": x[3]} for x in c]},
        backdrop=("wall",),
    )


def ball_bar(
    angle_deg: float = 20.0, length: float = 300.0, radius: float = 25.0, rig_z: float = 1000.0
) -> Scene:
    a = np.radians(angle_deg)
    mid = np.array([0.0, 0.0, rig_z - 900.0])
    half = 0.5 * length * np.array([np.cos(a), np.sin(a), 0.0])
    c1, c2 = mid - half, mid + half
    prims: list[Primitive] = [
        Sphere(c1, radius, name="ball1"),
        Sphere(c2, radius, name="ball2"),
        backdrop_wall(rig_z - 1150.0, 0.55),
    ]
    return Scene(
        "ballbar",
        prims,
        {
            "spheres": [
                {"centre": c1.tolist(), "radius": radius},
                {"centre": c2.tolist(), "radius": radius},
            ],
            "length": length,
        },
        backdrop=("wall",),
    )


def large_plane(tilt_deg: float = 15.0, rig_z: float = 1000.0) -> Scene:
    t = np.radians(tilt_deg)
    normal = np.array([np.sin(t), 0.3 * np.sin(t), np.cos(t)])
    p = Polygon((0, 0, rig_z - 920.0), normal, texture=constant(0.7), name="plane")
    return Scene("plane", [p], {"plane": p.plane.tolist()})


def steps(rig_z: float = 1000.0) -> Scene:
    """Boxes on a wall: depth jumps of 100-250 mm shift slits by several spacings, cast shadows."""
    wall_z = rig_z - 1100.0
    prims: list[Primitive] = [
        Box((-130.0, 0.0, wall_z + 125.0), (60.0, 150.0, 125.0), name="box_tall"),
        Box((40.0, -60.0, wall_z + 75.0), (50.0, 80.0, 75.0), texture_albedo=0.5, name="box_low"),
        Box(
            (160.0, 60.0, wall_z + 200.0), (40.0, 60.0, 40.0), texture_albedo=0.85, name="box_float"
        ),
        backdrop_wall(wall_z, 0.6),
    ]
    return Scene("steps", prims, {}, backdrop=("wall",))


def box_tops(rig_z: float = 1000.0) -> Scene:
    """Two boxes low in the view, their tops seen from above (as on a conveyor): on the tops
    the stripes lean far towards the horizontal, 72-74 degrees from the vertical on the flat
    top, 79-80 on the top of the box turned 11 degrees about the viewing axis (the default
    rig; a stripe leans the further, the nearer its surface's plane passes to the projector's
    height at the rig, and the more grazing the projector's light on it). ``info["tops"]``
    names the boxes and their tops' normals (the boxes' local y axis)."""
    wall_z = rig_z - 1150.0
    flat = Box((-90.0, -185.0, rig_z - 890.0), (75.0, 28.0, 100.0), np.eye(3), 0.7, "box_flat")
    c, s = np.cos(0.2), np.sin(0.2)
    turned = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # rows: local x, y, z
    rolled = Box((120.0, -140.0, rig_z - 880.0), (70.0, 25.0, 90.0), turned, 0.6, "box_turned")
    tops = [{"name": b.name, "normal": b.A[1].tolist()} for b in (flat, rolled)]
    return Scene(
        "box_tops", [flat, rolled, backdrop_wall(wall_z, 0.5)], {"tops": tops}, backdrop=("wall",)
    )


def freeform(rig_z: float = 1000.0) -> Scene:
    """A smooth free-form body (the paper's doll, as a sum of Gaussian bumps) before a wall."""
    wall_z = rig_z - 1100.0
    bumps = np.array(
        [
            [0.0, -40.0, 70.0, 110.0, 140.0],  # body
            [0.0, 120.0, 45.0, 45.0, 120.0],  # head
            [-90.0, -10.0, 25.0, 70.0, 70.0],  # arms
            [90.0, -10.0, 25.0, 70.0, 70.0],
        ]
    )
    hf = HeightField((0.0, 0.0, wall_z), (0, 0, 1), bumps, half_a=200.0, half_b=220.0, name="doll")
    return Scene("freeform", [hf, backdrop_wall(wall_z, 0.55)], {}, backdrop=("wall",))


def textured(rig_z: float = 1000.0, seed: int = 7) -> Scene:
    """A tilted plane with a printed texture and paint changes (albedo 0.15-0.9)."""
    rng = np.random.default_rng(seed)
    tex_noise = noise_texture(rng, 6.0, 0.15, 0.9)
    steps_tex = albedo_steps(70.0, [1.0, 0.45, 0.8, 0.3])

    def tex(a: F64, b: F64) -> F64:
        return tex_noise(a, b) * steps_tex(a, b)

    p = Polygon((0, 0, rig_z - 900.0), (0.2, -0.1, 1.0), texture=tex, name="textured")
    return Scene("textured", [p], {"plane": p.plane.tolist()})


SCENES: dict[str, Callable[[], Scene]] = {
    "holes": holes_board,
    "holes_tilted": lambda: holes_board(tilt_deg=20.0),
    "spheres": spheres,
    "ballbar": ball_bar,
    "plane": large_plane,
    "steps": steps,
    "box_tops": box_tops,
    "freeform": freeform,
    "textured": textured,
}


def make_scene(name: str) -> Scene:
    """A named scan scene (see ``SCENES``)."""
    try:
        return SCENES[name]()
    except KeyError:
        raise MultislitError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}") from None
