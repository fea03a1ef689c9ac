"""Rare-case predicates on hand-built scenes: where each must hold, where it must not, and at its threshold.

Scenes are real MuJoCo worlds (world.build_world) with objects snapped onto their catalog resting poses
(snap_to_rest); they are either forwarded at the snapped state or settled (scenegen.settle.physics) where
physics is the point (stacking). Values are checked against hand computations; each threshold is set
exactly at the measured quantity and one float step beside it, to show that ``holds`` flips at the
comparison the predicate documents. The occluded and low_light predicates are cross-checked against
real renders (scenegen.render.offscreen.SceneRenderer, MUJOCO_GL=egl from conftest.py).
"""

from __future__ import annotations

import inspect
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
import pytest
from scenes import place, proposal

from scenegen.assets.catalog import Catalog, load_catalog
from scenegen.core import layout
from scenegen.core.layout import FURNITURE_HOME
from scenegen.core.rotations import quat_to_matrix
from scenegen.propose.procedural import DEFAULT_CAMERAS
from scenegen.render.offscreen import SceneRenderer, segmentation_ids
from scenegen.schema.condition import RARE_TAGS, Condition
from scenegen.schema.scene import (
    Camera,
    FurniturePlacement,
    Light,
    Lighting,
    ObjectPlacement,
    TagValue,
)
from scenegen.settle.physics import SettleSettings, contact_configuration, settle
from scenegen.sim import world
from scenegen.tags import predicates as tags
from scenegen.tags.predicates import TagSettings

DEFAULTS = TagSettings()
MAIN = DEFAULT_CAMERAS[0]  # "front": x = 1.25, looking at -x
FRONT = Camera(name="front", position=MAIN.position, lookat=MAIN.lookat, width=160, height=120)
SX, SY = FURNITURE_HOME["shelf"]
SHELF = FurniturePlacement(name="shelf", kind="shelf", position=(SX, SY, 0.0))
HX, HY = layout.TABLE_SIZE[0] / 2, layout.TABLE_SIZE[1] / 2
BOX_HALF = 0.03  # small_box footprint half side (m); 0.05 tall
BOARD_UNDERSIDE = layout.TABLE_TOP_Z + 0.22  # the shelf board spans 0.22..0.24 m above the table top

# A lamp straight above the table centre; with ambient 0.3 no scene lit by it is low_light.
LAMP = Light(position=(0.0, 0.0, 2.5), direction=(0.0, 0.0, -1.0), intensity=1.0)
LIT = Lighting(lights=(LAMP,), ambient=(0.3, 0.3, 0.3))
DIM = Lighting(lights=(), ambient=(0.05, 0.05, 0.05))  # no lights at all
BRIGHT = Lighting(lights=(LAMP,), ambient=(0.05, 0.05, 0.05))
SHELF_LAMP = Light(position=(SX, SY, 2.5), direction=(0.0, 0.0, -1.0), intensity=1.0)
UNDER_LAMP = Lighting(lights=(SHELF_LAMP,), ambient=(0.1, 0.1, 0.1))
# The same lamp without a shadow map (what the procedural proposer gives every light after the first).
UNDER_LAMP_NO_SHADOW = Lighting(
    lights=(SHELF_LAMP.model_copy(update={"cast_shadow": False}),), ambient=(0.1, 0.1, 0.1)
)


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


# ---------------------------------------------------------------- hand-built scenes


@dataclass
class Recipe:
    objects: list[ObjectPlacement]
    furniture: tuple[FurniturePlacement, ...] = ()
    lighting: Lighting = LIT
    target: str | None = None  # default: the first object
    settled: bool = False  # run scenegen.settle.physics instead of forwarding the snapped state


@dataclass
class Scene:
    recipe: Recipe
    model: mujoco.MjModel
    data: mujoco.MjData
    contacts: list = field(default_factory=list)

    def ctx(self, target: str | None = None) -> tags.TagContext:
        r = self.recipe
        return tags.TagContext.of_scene(
            self.model,
            self.data,
            load_catalog(),
            target or r.target or r.objects[0].name,
            r.objects,
            r.furniture,
            r.lighting,
            FRONT.position,
            self.contacts,
        )

    def tag(self, name: str, target: str | None = None, **settings) -> TagValue:
        return tags.PREDICATES[name](self.ctx(target), TagSettings(**settings))


def build(catalog: Catalog, r: Recipe) -> Scene:
    objects = tuple(r.objects)
    p = proposal(objects, r.furniture, r.target, lighting=r.lighting, cameras=(FRONT,))
    model = world.build_world(catalog, objects, r.furniture, r.lighting, [FRONT]).compile()
    qpos, ctrl = world.initial_state(model, p.condition.robot_pose, objects)
    if r.settled:
        outcome = settle(model, p, qpos, ctrl, SettleSettings(), catalog)
        assert outcome.passed, outcome.checks
        qpos = outcome.qpos
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = qpos, ctrl
    mujoco.mj_forward(model, data)
    contacts = contact_configuration(model, qpos, [o.name for o in objects])
    return Scene(r, model, data, contacts)


RECIPES: dict[str, Callable[[Catalog], Recipe]] = {}


def recipe(fn: Callable[[Catalog], Recipe]) -> Callable[[Catalog], Recipe]:
    RECIPES[fn.__name__] = fn
    return fn


@recipe
def box_centre(c):
    return Recipe([place(c, "box", "small_box", 0.0, 0.0)])


@recipe
def box_2cm_from_edge(c):
    return Recipe([place(c, "box", "small_box", HX - BOX_HALF - 0.02, 0.0)])


@recipe
def box_3cm_from_edge(c):
    return Recipe([place(c, "box", "small_box", HX - BOX_HALF - 0.03, 0.0)])


@recipe
def box_turned_near_edge(c):
    # Turned 45 degrees, its corner reaches 3*sqrt(2) cm towards the edge: 2.76 cm from it, though its
    # centre is 7 cm away and an unturned box there would be 4 cm from it.
    return Recipe([place(c, "box", "small_box", HX - 0.07, 0.0, yaw=math.pi / 4)])


@recipe
def box_near_side_edge(c):
    return Recipe([place(c, "box", "small_box", 0.0, -(HY - BOX_HALF - 0.01))])


@recipe
def box_overhanging(c):
    return Recipe([place(c, "box", "small_box", HX - BOX_HALF + 0.02, 0.0)])


@recipe
def box_on_floor(c):
    return Recipe([place(c, "box", "small_box", 0.1, layout.FLOOR.center[1], support="floor")])


@recipe
def stack(c):
    base = place(c, "base", "small_box", 0.1, -0.1)
    top = place(c, "top", "small_box", 0.1, -0.1, support="base", below=[base])
    return Recipe([top, base], settled=True)


@recipe
def side_by_side(c):
    base = place(c, "base", "small_box", 0.1, -0.1)
    return Recipe([place(c, "top", "small_box", 0.1 + 2 * BOX_HALF, -0.1), base], settled=True)


@recipe
def box_on_shelf(c):
    return Recipe([place(c, "box", "small_box", SX, SY, support="shelf", furniture=[SHELF])], (SHELF,))


@recipe
def box_under_shelf(c):
    return Recipe([place(c, "box", "small_box", SX, SY)], (SHELF,))


@recipe
def box_half_under_shelf(c):
    # Centred on the back edge of the board (x = SX - 0.13): half of the footprint is under it.
    return Recipe([place(c, "box", "small_box", SX - 0.13, SY)], (SHELF,))


@recipe
def box_beside_shelf(c):
    return Recipe([place(c, "box", "small_box", SX, SY - 0.3)], (SHELF,))


@recipe
def mug_upright(c):
    return Recipe([place(c, "mug", "mug", 0.0, 0.0, pose=2, yaw=0.7)])


@recipe
def mug_on_its_side(c):
    return Recipe([place(c, "mug", "mug", 0.0, 0.0, pose=0, yaw=0.7)])


@recipe
def mug_upside_down(c):
    return Recipe([place(c, "mug", "mug", 0.0, 0.0, pose=3, yaw=0.7)])


@recipe
def teaspoon_bowl_down(c):
    return Recipe([place(c, "spoon", "teaspoon", 0.0, 0.0, pose=0, yaw=0.5)])


@recipe
def teaspoon_bowl_up(c):
    return Recipe([place(c, "spoon", "teaspoon", 0.0, 0.0, pose=1, yaw=0.5)])


def _wall(c, y):
    """A cereal box standing on its 14 cm side, 5 cm thick along x, 20 cm wide along y."""
    return place(c, "wall", "cereal_box", BOX_HALF + 0.025 + 0.01, y, pose=2)


@recipe
def box_behind_cereal_box(c):
    return Recipe([place(c, "box", "small_box", 0.0, 0.0), _wall(c, 0.0)])


@recipe
def box_beside_cereal_box(c):
    return Recipe([place(c, "box", "small_box", 0.0, 0.0), _wall(c, 0.2)])


@recipe
def can_alone(c):
    return Recipe([place(c, "can", "soup_can", 0.0, 0.0, pose=1)])


@recipe
def can_half_behind_cereal_box(c):
    return Recipe([place(c, "can", "soup_can", 0.0, 0.0, pose=1), _wall(c, 0.1)])


# Clutter around a box at the origin, relative to the default radius R: centres at R - 5 cm, R - 3 cm
# and exactly R, one 1.3 mm outside and one far away.
R = DEFAULTS.clutter_radius
JUST_OUTSIDE = (R + 0.0013) / math.sqrt(2)
CLUTTER_INSIDE = [(R - 0.05, 0.0), (0.0, R - 0.03), (0.0, -R)]
CLUTTER_OUTSIDE = [(JUST_OUTSIDE, JUST_OUTSIDE), (0.3, -0.35)]


@recipe
def clutter(c):
    others = [
        place(c, f"can{i}", "soda_can", x, y, pose=1)
        for i, (x, y) in enumerate(CLUTTER_INSIDE + CLUTTER_OUTSIDE)
    ]
    return Recipe([place(c, "box", "small_box", 0.0, 0.0), *others])


@recipe
def box_dim(c):
    return Recipe([place(c, "box", "small_box", 0.0, 0.0)], lighting=DIM)


@recipe
def box_bright(c):
    return Recipe([place(c, "box", "small_box", 0.0, 0.0)], lighting=BRIGHT)


@recipe
def box_light_aimed_away(c):
    away = Light(position=(0.0, 0.0, 2.5), direction=(1.0, 0.0, 0.0), intensity=1.0)
    lighting = Lighting(lights=(away,), ambient=DIM.ambient)
    return Recipe([place(c, "box", "small_box", 0.0, 0.0)], lighting=lighting)


@recipe
def box_shadowed(c):
    return Recipe([place(c, "box", "small_box", SX, SY)], (SHELF,), UNDER_LAMP)


@recipe
def box_sunlit(c):
    return Recipe([place(c, "box", "small_box", SX, SY - 0.3)], (SHELF,), UNDER_LAMP)


@recipe
def box_under_shelf_no_shadow_light(c):
    return Recipe([place(c, "box", "small_box", SX, SY)], (SHELF,), UNDER_LAMP_NO_SHADOW)


@recipe
def box_beside_shelf_no_shadow_light(c):
    return Recipe([place(c, "box", "small_box", SX, SY - 0.3)], (SHELF,), UNDER_LAMP_NO_SHADOW)


class Scenes:
    """Scenes by recipe name, built once per module."""

    def __init__(self, catalog):
        self.catalog = catalog
        self._built: dict[str, Scene] = {}

    def __getitem__(self, name: str) -> Scene:
        if name not in self._built:
            self._built[name] = build(self.catalog, RECIPES[name](self.catalog))
        return self._built[name]


@pytest.fixture(scope="module")
def scenes(catalog):
    return Scenes(catalog)


def collision_vertices(scene: Scene, body: str) -> np.ndarray:
    """World-frame vertices of a body's convex collision parts (group 3), straight from MuJoCo."""
    m, d = scene.model, scene.data
    out = []
    for g in np.flatnonzero(m.geom_bodyid == m.body(body).id):
        if m.geom_group[g] != world.COLLISION_GROUP:
            continue
        mesh = m.geom_dataid[g]
        verts = m.mesh_vert[m.mesh_vertadr[mesh] : m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
        out.append(verts @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g])
    return np.concatenate(out)


def below(x: float) -> float:
    return math.nextafter(x, -math.inf)


def above(x: float) -> float:
    return math.nextafter(x, math.inf)


# ---------------------------------------------------------------- registry, nominal, version


def test_every_rare_tag_has_a_predicate(scenes):
    assert set(tags.PREDICATES) == set(RARE_TAGS)
    measured = tags.measure_tags(scenes["box_centre"].ctx())
    assert list(measured) == [*tags.PREDICATES, "nominal"]
    for name, value in measured.items():
        assert value.unit and math.isfinite(value.value) and math.isfinite(value.threshold), name


@pytest.mark.parametrize("name", list(RECIPES))
def test_nominal_holds_iff_no_rare_tag_holds(scenes, name):
    measured = tags.measure_tags(scenes[name].ctx())
    held = [t for t in RARE_TAGS if measured[t].holds]
    assert measured["nominal"].holds is (not held)
    assert measured["nominal"].value == len(held)
    assert measured["nominal"].threshold == 0.0


def test_a_plain_scene_is_nominal(scenes):
    measured = tags.measure_tags(scenes["box_centre"].ctx())
    assert [t for t, v in measured.items() if v.holds] == ["nominal"]


def test_nominal_counts_every_rare_tag_held(scenes):
    # Under the shelf with only the lamp above it: shadowed (low_light) and under the overhang.
    measured = tags.measure_tags(scenes["box_shadowed"].ctx())
    assert {t for t in RARE_TAGS if measured[t].holds} == {"under_overhang", "low_light"}
    assert not measured["nominal"].holds and measured["nominal"].value == 2.0


def test_predicate_version_is_an_explicit_constant():
    """A literal in tags.py, not derived from its text: editing the module without changing an output
    keeps it; tests/tags/test_predicate_panel.py fails when an output changes and it is not bumped."""
    assert re.fullmatch(r"[0-9a-f]{16}", tags.PREDICATE_VERSION)
    assert f'\nPREDICATE_VERSION = "{tags.PREDICATE_VERSION}"\n' in inspect.getsource(tags)
    assert not any(name in vars(tags) for name in ("hashlib", "_version"))


# ---------------------------------------------------------------- near_edge


@pytest.mark.parametrize(
    ("name", "margin", "holds"),
    [
        ("box_centre", HX - BOX_HALF, False),
        ("box_2cm_from_edge", 0.02, True),
        ("box_turned_near_edge", 0.07 - BOX_HALF * math.sqrt(2), True),
        ("box_near_side_edge", 0.01, True),
        ("box_overhanging", -0.02, True),
    ],
)
def test_near_edge_is_the_footprint_distance_to_the_nearest_table_edge(scenes, name, margin, holds):
    value = scenes[name].tag("near_edge")
    assert value.value == pytest.approx(margin, abs=1e-6)
    assert value.holds is holds
    assert value.threshold == DEFAULTS.near_edge_distance and value.unit == "m"


def test_near_edge_threshold_is_inclusive(scenes):
    scene = scenes["box_3cm_from_edge"]
    pts = collision_vertices(scene, "box")
    margin = float(min((HX - np.abs(pts[:, 0])).min(), (HY - np.abs(pts[:, 1])).min()))
    assert margin == pytest.approx(0.03, abs=1e-6)  # 3 cm, up to the float32 mesh vertices
    # Tags compare the value as stored (rounded to 6 decimals), so thresholds step by 1e-6.
    margin = round(margin, 6)
    at = scene.tag("near_edge", near_edge_distance=margin)
    assert at.holds and at.value == margin
    assert not scene.tag("near_edge", near_edge_distance=margin - 1e-6).holds
    # The 2 cm box flips between thresholds 2 cm +- 1 um.
    assert scenes["box_2cm_from_edge"].tag("near_edge", near_edge_distance=0.020001).holds
    assert not scenes["box_2cm_from_edge"].tag("near_edge", near_edge_distance=0.019999).holds


def test_near_edge_does_not_hold_off_the_table(scenes):
    # On the floor strip beside the table its footprint is 'past' the edge, but it is not on the table.
    value = scenes["box_on_floor"].tag("near_edge")
    assert value.value < 0.0 and not value.holds


# ---------------------------------------------------------------- on_floor


def test_on_floor_holds_for_an_object_on_the_floor_strip(scenes):
    scene = scenes["box_on_floor"]
    assert ("box", "world", "rests_on") in {(c.a, c.b, c.kind) for c in scene.contacts}
    value = scene.tag("on_floor")
    assert value.holds and value.unit == "m"
    assert value.value == pytest.approx(layout.TABLE_TOP_Z - 0.025, abs=1e-6)


def test_on_floor_does_not_hold_on_the_table(scenes):
    value = scenes["box_centre"].tag("on_floor")
    assert not value.holds
    assert value.value == pytest.approx(-0.025, abs=1e-6)  # the centre is 2.5 cm above the top


def test_on_floor_threshold_is_inclusive(scenes):
    scene = scenes["box_on_floor"]
    drop = layout.TABLE_TOP_Z - float(scene.data.body("box").xpos[2])
    assert scene.tag("on_floor", on_floor_drop=drop).holds
    assert not scene.tag("on_floor", on_floor_drop=above(drop)).holds


# ---------------------------------------------------------------- stacked


def test_box_settled_on_a_box_is_stacked(scenes):
    scene = scenes["stack"]
    assert ("top", "base", "rests_on") in {(c.a, c.b, c.kind) for c in scene.contacts}
    value = scene.tag("stacked")
    assert value.holds and value.value == 1.0 == value.threshold  # one support: at the threshold
    # It came to rest on top of the other box.
    assert scene.data.body("top").xpos[2] == pytest.approx(layout.TABLE_TOP_Z + 0.075, abs=2e-3)


def test_the_bottom_of_a_stack_is_not_stacked(scenes):
    value = scenes["stack"].tag("stacked", target="base")
    assert not value.holds and value.value == 0.0


def test_boxes_side_by_side_are_not_stacked(scenes):
    scene = scenes["side_by_side"]
    kinds = {(c.a, c.b): c.kind for c in scene.contacts}
    assert kinds[("top", "table")] == "rests_on"
    assert kinds.get(("top", "base"), "touches") == "touches"
    value = scene.tag("stacked")
    assert not value.holds and value.value == 0.0


def test_resting_on_furniture_is_not_stacked(scenes):
    scene = scenes["box_on_shelf"]
    assert ("box", "shelf", "rests_on") in {(c.a, c.b, c.kind) for c in scene.contacts}
    assert not scene.tag("stacked").holds


# ---------------------------------------------------------------- under_overhang


def test_short_object_under_the_shelf_board_is_under_the_overhang(scenes):
    assert layout.TABLE_TOP_Z + 0.05 < BOARD_UNDERSIDE
    value = scenes["box_under_shelf"].tag("under_overhang")
    assert value.holds and value.value == 1.0 and value.unit == "fraction"


@pytest.mark.parametrize("name", ["box_beside_shelf", "box_on_shelf", "box_centre"])
def test_object_beside_or_on_the_shelf_is_not_under_the_overhang(scenes, name):
    value = scenes[name].tag("under_overhang")
    assert not value.holds and value.value == 0.0


def test_under_overhang_threshold_is_inclusive(scenes):
    # Half of the box's footprint (4 of its 8 hull vertices) lies under the board's back edge.
    scene = scenes["box_half_under_shelf"]
    value = scene.tag("under_overhang")
    assert value.value == 0.5 == DEFAULTS.overhang_cover
    assert value.holds
    assert not scene.tag("under_overhang", overhang_cover=above(0.5)).holds


# ---------------------------------------------------------------- toppled


def test_upright_mug_is_not_toppled(scenes, catalog):
    assert catalog.get("mug").resting_poses[2].upright
    value = scenes["mug_upright"].tag("toppled")
    assert not value.holds
    assert value.value == pytest.approx(0.0, abs=1e-6)
    assert value.threshold == round(DEFAULTS.toppled_angle, 6) and value.unit == "rad"


@pytest.mark.parametrize(("name", "angle"), [("mug_on_its_side", math.pi / 2), ("mug_upside_down", math.pi)])
def test_mug_on_its_side_or_upside_down_is_toppled(scenes, catalog, name, angle):
    pose = int(scenes[name].recipe.objects[0].resting_pose)
    assert not catalog.get("mug").resting_poses[pose].upright
    value = scenes[name].tag("toppled")
    assert value.holds and value.value == pytest.approx(angle, abs=1e-5)


def test_toppled_threshold_is_exclusive(scenes):
    scene = scenes["mug_on_its_side"]
    # The mug's one upright pose has its authored +z up, so the angle is that of the body z axis.
    up = scene.data.body("mug").xmat.reshape(3, 3)[2, 2]
    angle = round(math.acos(max(-1.0, min(1.0, float(up)))), 6)  # compared as stored
    assert not scene.tag("toppled", toppled_angle=angle).holds
    assert scene.tag("toppled", toppled_angle=angle - 1e-6).holds


@pytest.mark.parametrize("name", ["teaspoon_bowl_down", "teaspoon_bowl_up"])
def test_flat_utensil_on_either_face_is_not_toppled(scenes, catalog, name):
    assert all(p.upright for p in catalog.get("teaspoon").resting_poses)  # flat asset: both faces
    scene = scenes[name]
    value = scene.tag("toppled")
    assert not value.holds
    assert value.value == pytest.approx(0.0, abs=1e-5)
    assert scene.ctx().upright_axes.shape == (2, 3)


def test_flat_utensil_bowl_down_is_upside_down_in_its_authored_frame(scenes, catalog):
    # What makes the flat flag matter: lying bowl down, the spoon's authored +z points down.
    scene = scenes["teaspoon_bowl_down"]
    assert scene.data.body("spoon").xmat.reshape(3, 3)[2, 2] < -0.99
    expected = quat_to_matrix(catalog.get("teaspoon").resting_poses[0].quat)[2, :]
    assert scene.ctx().upright_axes[0] == pytest.approx(expected)


# ---------------------------------------------------------------- occluded


def test_box_behind_a_cereal_box_is_occluded(scenes):
    value = scenes["box_behind_cereal_box"].tag("occluded")
    assert value.holds and value.value == 1.0 and value.unit == "fraction"
    # Fully hidden: holds even at the strictest threshold.
    assert scenes["box_behind_cereal_box"].tag("occluded", occluded_fraction=1.0).holds


@pytest.mark.parametrize("name", ["box_centre", "box_beside_cereal_box"])
def test_box_in_the_open_is_not_occluded(scenes, name):
    value = scenes[name].tag("occluded")
    assert not value.holds and value.value == 0.0


def test_occluded_threshold_is_inclusive(scenes):
    scene = scenes["can_half_behind_cereal_box"]
    value = scene.tag("occluded")
    n = DEFAULTS.occlusion_points
    hidden = round(value.value * n)
    assert 0 < hidden < n and value.value == pytest.approx(hidden / n, abs=1e-6)
    fraction = round(hidden / n, 6)  # compared as stored
    assert scene.tag("occluded", occluded_fraction=fraction).holds
    assert not scene.tag("occluded", occluded_fraction=fraction + 1e-6).holds


# ---------------------------------------------------------------- clutter


def test_clutter_counts_objects_within_the_radius(scenes):
    scene = scenes["clutter"]
    t = scene.data.body("box").xpos[:2]
    dist = {f"can{i}": float(np.linalg.norm(scene.data.body(f"can{i}").xpos[:2] - t)) for i in range(5)}
    assert dist["can2"] == DEFAULTS.clutter_radius  # exactly on the radius: inside
    assert DEFAULTS.clutter_radius < dist["can3"] < DEFAULTS.clutter_radius + 0.002  # just outside
    value = scene.tag("clutter")
    assert value.value == len(CLUTTER_INSIDE) == 3
    assert value.holds and value.threshold == DEFAULTS.clutter_count == 3  # at the threshold
    assert value.unit == "objects"


def test_clutter_thresholds(scenes):
    scene = scenes["clutter"]
    assert not scene.tag("clutter", clutter_count=4).holds
    # Shrinking the radius by one float step drops the can exactly on it.
    tighter = scene.tag("clutter", clutter_radius=below(DEFAULTS.clutter_radius))
    assert tighter.value == 2.0 and not tighter.holds
    # Growing it to the just-outside can brings that one in.
    wider = scene.tag("clutter", clutter_radius=R + 0.002, clutter_count=4)
    assert wider.value == 4.0 and wider.holds


def test_a_lone_object_is_not_cluttered(scenes):
    value = scenes["box_centre"].tag("clutter")
    assert value.value == 0.0 and not value.holds


# ---------------------------------------------------------------- low_light


def test_no_lights_and_dim_ambient_is_low_light(scenes):
    value = scenes["box_dim"].tag("low_light")
    assert value.holds and value.unit == "irradiance"
    assert value.value == pytest.approx(0.05)


def test_bright_light_straight_above_is_not_low_light(scenes):
    value = scenes["box_bright"].tag("low_light")
    assert not value.holds
    # ambient + colour 1 x intensity 1 x spot falloff 1 x incidence 1 (the lamp is straight above)
    assert value.value == pytest.approx(0.05 + 1.0, abs=1e-6)


def test_light_aimed_away_adds_nothing(scenes):
    assert scenes["box_light_aimed_away"].tag("low_light").value == pytest.approx(0.05)


def test_low_light_threshold_is_exclusive(scenes):
    scene = scenes["box_dim"]
    irradiance = round(float(np.mean(DIM.ambient)), 6)  # compared as stored
    assert not scene.tag("low_light", low_light_irradiance=irradiance).holds
    assert scene.tag("low_light", low_light_irradiance=irradiance + 1e-6).holds


def test_shelf_board_shadows_the_only_light(scenes):
    shadowed = scenes["box_shadowed"].tag("low_light")
    sunlit = scenes["box_sunlit"].tag("low_light")
    # Under the board only the ambient reaches the box.
    assert shadowed.value == pytest.approx(0.1) and shadowed.holds
    # Beside the shelf the lamp reaches it 0.3 m off its axis: spot falloff cos^10, incidence cos.
    top = np.array([SX, SY - 0.3, layout.TABLE_TOP_Z + 0.05 + 1e-3])
    to_lamp = np.asarray(SHELF_LAMP.position) - top
    cos = to_lamp[2] / np.linalg.norm(to_lamp)
    assert sunlit.value == pytest.approx(0.1 + cos**10 * cos, abs=1e-5)
    assert not sunlit.holds and sunlit.value > shadowed.value


# ---------------------------------------------------------------- condition_check


def test_condition_check_passes_when_the_condition_is_met(scenes):
    measured = tags.measure_tags(scenes["box_behind_cereal_box"].ctx())
    result = tags.condition_check(
        measured, Condition(target="box", tags={"occluded": "required", "near_edge": "forbidden"})
    )
    assert result.passed and result.label is None
    assert result.value == 0.0 and result.detail == ""
    assert result.stage == "tag" and result.check == "condition"


def test_missing_required_tag_is_condition_unmet_with_its_value(scenes):
    measured = tags.measure_tags(scenes["box_centre"].ctx())
    result = tags.condition_check(measured, Condition(target="box", tags={"near_edge": "required"}))
    assert not result.passed and result.label == "condition_unmet"
    assert result.value == 1.0
    assert result.detail == "required near_edge = 0.37 m (threshold 0.03)"


def test_present_forbidden_tag_is_condition_unmet_with_its_value(scenes):
    measured = tags.measure_tags(scenes["box_behind_cereal_box"].ctx())
    result = tags.condition_check(measured, Condition(target="box", tags={"occluded": "forbidden"}))
    assert not result.passed and result.label == "condition_unmet"
    assert result.detail == "forbidden occluded = 1.0 fraction (threshold 0.5)"


def test_condition_unmet_lists_every_failing_tag(scenes):
    measured = tags.measure_tags(scenes["box_dim"].ctx())
    condition = Condition(target="box", tags={"stacked": "required", "low_light": "forbidden"})
    result = tags.condition_check(measured, condition)
    assert not result.passed and result.value == 2.0
    assert result.detail == (
        "required stacked = 0.0 objects (threshold 1.0); "
        "forbidden low_light = 0.05 irradiance (threshold 0.25)"
    )


# ---------------------------------------------------------------- rendered cross-checks


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer()
    yield r
    r.close()


def target_pixels(renderer: SceneRenderer, scene: Scene) -> np.ndarray:
    """RGB (N, 3) of the target's pixels in the main camera's render (segmentation mask)."""
    r = scene.recipe
    ids = segmentation_ids(scene.model, [o.name for o in r.objects], [f.name for f in r.furniture])
    frames = renderer.render(scene.model, scene.data, [FRONT.name], ids, [(FRONT.width, FRONT.height)])[0]
    target = r.target or r.objects[0].name
    return frames.rgb[frames.seg == ids[target]].astype(float)


def test_occluded_agrees_with_the_rendered_segmentation(scenes, renderer):
    # Pixels of the target with the cereal box in front of it / beside it, relative to no cereal box.
    alone = len(target_pixels(renderer, scenes["box_centre"]))
    assert alone > 20
    hidden = scenes["box_behind_cereal_box"]
    visible = len(target_pixels(renderer, hidden)) / alone
    assert hidden.tag("occluded").holds and visible < 0.5
    beside = scenes["box_beside_cereal_box"]
    visible = len(target_pixels(renderer, beside)) / alone
    assert not beside.tag("occluded").holds and visible > 0.95
    # Partly hidden: the predicate's hidden fraction is close to the rendered one.
    can_alone = len(target_pixels(renderer, scenes["can_alone"]))
    half = scenes["can_half_behind_cereal_box"]
    rendered_hidden = 1.0 - len(target_pixels(renderer, half)) / can_alone
    assert 0.2 < rendered_hidden < 0.8
    assert half.tag("occluded").value == pytest.approx(rendered_hidden, abs=0.1)


def _low_light_order(scenes, renderer, names):
    """(irradiance, mean RGB of the target's pixels) per scene."""
    out = {}
    for name in names:
        pixels = target_pixels(renderer, scenes[name])
        assert len(pixels) > 20, name
        out[name] = (scenes[name].tag("low_light").value, float(pixels.mean()))
    return out


def _assert_same_order(measured):
    # The predicate measures light on an upward surface at one point, the render averages every visible
    # face: only irradiances a factor 2 apart need to order the renders the same way.
    for a, (ea, ra) in measured.items():
        for b, (eb, rb) in measured.items():
            if eb > 2 * ea:
                assert rb > ra, (
                    f"{a}: irradiance {ea}, mean RGB {ra:.1f}; {b}: irradiance {eb}, mean RGB {rb:.1f}"
                )


def test_low_light_agrees_with_the_rendered_brightness(scenes, renderer):
    measured = _low_light_order(scenes, renderer, ["box_dim", "box_bright", "box_shadowed", "box_sunlit"])
    assert scenes["box_dim"].tag("low_light").holds and not scenes["box_bright"].tag("low_light").holds
    assert measured["box_dim"][1] < measured["box_bright"][1]
    assert scenes["box_shadowed"].tag("low_light").holds and not scenes["box_sunlit"].tag("low_light").holds
    assert measured["box_shadowed"][1] < measured["box_sunlit"][1]
    _assert_same_order(measured)


def test_low_light_agrees_with_the_render_for_a_light_without_shadows(scenes, renderer):
    # The procedural proposer gives every light after the first cast_shadow=False; the renderer then
    # draws no shadow of the shelf board, so the box under it is as bright as the one beside it.
    measured = _low_light_order(
        scenes, renderer, ["box_under_shelf_no_shadow_light", "box_beside_shelf_no_shadow_light"]
    )
    under, beside = measured["box_under_shelf_no_shadow_light"], measured["box_beside_shelf_no_shadow_light"]
    assert under[1] == pytest.approx(beside[1], rel=0.2)  # the render: no shadow
    _assert_same_order(measured)
