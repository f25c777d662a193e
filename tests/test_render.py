"""`render` draws what the geometry says: its PNG read back pixel by pixel against a float64 2D ray
cast of the room, the poses drawn, and the settings it writes beside the picture."""

import json

import matplotlib
import numpy as np

import scenes
from acoustic_sim.cli import main
from tests.pictures import axes_frames, colormap_value, densify, distances, near, outline, points_of, read_rgb

HOKUYO_AZIMUTH_RAD = np.deg2rad(np.linspace(-135.0, 135.0, 1081))  # 270 deg in 0.25 deg steps
IMAGE_AZIMUTH_DEG = (90.5, -90.5)  # the polar image's edges, left to right: bins of 1 deg centred on -90..90
IMAGE_RANGE_M = (0.2, 5.0)  # its range edges, bottom to top


def first_hits(origin, yaw, azimuth_rad, rectangle, circles=()):
    """Where horizontal rays from `origin` [m] (sensor heading `yaw` [rad]) first meet the inside
    of an axis-aligned rectangle (x0, y0, x1, y1) or a circle (cx, cy, r): (points (n, 2), range (n,))."""
    angle = yaw + np.asarray(azimuth_rad)
    d = np.c_[np.cos(angle), np.sin(angle)]
    with np.errstate(divide="ignore"):
        far = np.where(d > 0, np.array(rectangle[2:]) - origin, np.array(rectangle[:2]) - origin) / d
    t = np.abs(far).min(axis=1)
    for cx, cy, radius in circles:
        m = origin - np.array([cx, cy])
        b, c = d @ m, m @ m - radius**2
        disc = b**2 - c
        near_root = -b - np.sqrt(np.maximum(disc, 0.0))
        t = np.where((disc > 0) & (near_root > 0), np.minimum(t, near_root), t)
    return origin + t[:, None] * d, t


def yaw_of(pose):
    return float(np.arctan2(pose[1, 0], pose[0, 0]))


def top_view_scale(image, frame, outer_walls, point_colour):
    """Metres to pixels in the top view, from the room's outer walls as drawn (grey, or covered by
    `point_colour` points) and where they are: `outer_walls` (x0, y0, x1, y1) [m]."""
    walls = near(image, "0.25", 0.08) | near(image, point_colour, 0.1)
    left, right, top, bottom = outline(walls, frame)
    x0, y0, x1, y1 = outer_walls
    per_m_x, per_m_y = (right - left) / (x1 - x0), (bottom - top) / (y1 - y0)
    assert abs(per_m_x / per_m_y - 1.0) < 0.02, "the top view is drawn to one scale in x and y"

    def to_pixels(xy):
        xy = np.atleast_2d(xy)
        return np.c_[left + (xy[:, 0] - x0) * per_m_x, bottom - (xy[:, 1] - y0) * per_m_y]

    return to_pixels


def check_polar_lidar_image(image, frame, ranges_m):
    """The polar LiDAR image's dark cells are the beams' (azimuth, range) within the image (each
    drawn, none elsewhere): `ranges_m` (1081,) of the Hokuyo's beams."""
    azimuth_deg = np.rad2deg(HOKUYO_AZIMUTH_RAD)
    cells = points_of((image.max(axis=-1) < 0.3) & frame.inside(image.shape, inset=2))
    assert len(cells) > 100

    def beams(half_width_deg):
        seen = np.abs(azimuth_deg) <= half_width_deg
        seen &= (ranges_m >= IMAGE_RANGE_M[0]) & (ranges_m < IMAGE_RANGE_M[1])
        return frame.to_pixels(azimuth_deg[seen], ranges_m[seen], IMAGE_AZIMUTH_DEG, IMAGE_RANGE_M)

    # A cell is 3 px wide and 2 px high: its pixels lie within 4 px of a beam that fills it (the
    # outer bins take beams up to 90.5 deg).
    assert distances(cells, densify(beams(90.5))).max() <= 4.0, "a dark cell where no beam returns"
    assert distances(beams(90.0), cells).max() <= 4.0, "a beam's return not drawn"


def test_render_draws_the_scan_and_the_trajectory_where_the_room_puts_them(tmp_path, device):
    """box_room (6 x 4 m), 30 poses at 0.8 m/s, frame 12. Top view, scaled by the walls as drawn:
    the red LiDAR points are where frame 12's 1081 beams meet the walls (a float64 2D ray cast),
    every one drawn (within 3 px, 2.7 cm); the blue trajectory follows the poses, with the start
    dot at the first. Polar image: the dark cells are the same beams' (azimuth, range)."""
    out = tmp_path / "room.png"
    argv = ["render", "--scene", "box_room", "--frames", "30", "--frame", "12", "--speed", "0.8"]
    assert main([*argv, "--device", device, "--out", str(out)]) == 0
    image = read_rgb(out)
    top_view, polar = sorted(axes_frames(image), key=lambda box: box.left)
    scene = scenes.box_room(seed=0)
    poses = scenes.trajectory(scene, frames=30, dt=0.1, speed=0.8, seed=0)
    to_pixels = top_view_scale(image, top_view, (0.0, 0.0, 6.0, 4.0), "tab:red")

    hits, ranges_m = first_hits(poses[12, :2, 3], yaw_of(poses[12]), HOKUYO_AZIMUTH_RAD, (0.0, 0.0, 6.0, 4.0))
    want = to_pixels(hits)
    red = points_of(near(image, "tab:red", 0.1) & top_view.inside(image.shape))
    assert distances(red, densify(want)).max() <= 3.0, "a LiDAR point off the walls frame 12 sees"
    assert distances(want, red).max() <= 3.0, "a beam's return not drawn"

    path = densify(to_pixels(poses[:, :2, 3]))
    blue = points_of(near(image, "tab:blue", 0.1) & top_view.inside(image.shape))
    assert distances(blue, path).max() <= 6.0, "blue drawn off the trajectory"  # the start dot: radius 4.6 px
    before = densify(to_pixels(poses[:13, :2, 3]))  # past frame 12 the heading arrow covers the path
    assert np.mean(distances(before, blue) <= 2.0) > 0.97, "the trajectory up to frame 12 is not drawn"
    start, middle = (np.sum(distances(blue, to_pixels(poses[i, :2, 3])) <= 3.0) for i in (0, 6))
    assert start > 20 > middle, (start, middle)  # a filled dot at the start, a line through frame 6

    check_polar_lidar_image(image, polar, ranges_m)


def test_render_svg_plan_with_a_pillar(tmp_path, device):
    """An SVG plan: a 600 x 400 rectangle with a circle of radius 40 at its centre, at 1 cm per
    unit, moved 10 cm in x and y (the floor reaches 5 cm past the walls): walls 10 cm thick centred
    on the strokes at 0.1 and 6.1 / 4.1 m (outer faces at 0.05 and 6.15 / 4.15 m, inner faces at
    0.15 and 6.05 / 4.05 m), a pillar of radius 0.4 m at (3.1, 2.1). The LiDAR points of the drawn
    frame lie on the inner faces or the pillar, as a 2D ray cast puts them, each one drawn; the
    settings file names the plan and the scene arguments."""
    plan = tmp_path / "plan.svg"
    plan.write_text(
        '<svg xmlns="http://www.w3.org/2000/svg"><rect x="0" y="0" width="600" height="400"/>'
        '<circle cx="300" cy="200" r="40"/></svg>'
    )
    out = tmp_path / "plan.png"
    argv = ["render", "--svg", str(plan), "--scene-arg", "wall_height=2.0", "--frames", "5", "--frame", "4"]
    assert main([*argv, "--device", device, "--out", str(out)]) == 0
    written = json.loads(out.with_suffix(".json").read_text())
    assert written["options"]["svg"] == str(plan) and written["options"]["scene_arg"] == ["wall_height=2.0"]
    image = read_rgb(out)
    top_view, polar = sorted(axes_frames(image), key=lambda box: box.left)
    scene = scenes.from_svg(plan, wall_height=2.0)
    pose = scenes.trajectory(scene, frames=5, seed=0)[4]
    to_pixels = top_view_scale(image, top_view, (0.05, 0.05, 6.15, 4.15), "tab:red")
    hits, ranges_m = first_hits(
        pose[:2, 3], yaw_of(pose), HOKUYO_AZIMUTH_RAD, (0.15, 0.15, 6.05, 4.05), circles=[(3.1, 2.1, 0.4)]
    )
    red = points_of(near(image, "tab:red", 0.1) & top_view.inside(image.shape))
    want = to_pixels(hits)
    assert np.sum(np.linalg.norm(hits - (3.1, 2.1), axis=1) < 0.45) > 10  # the pillar casts a shadow
    # The pillar is a polygon of 32 sides: 2 mm inside its circle at most.
    assert distances(red, densify(want)).max() <= 3.0, "a LiDAR point off the plan's inner faces and pillar"
    assert distances(want, red).max() <= 3.0, "a beam's return not drawn"
    check_polar_lidar_image(image, polar, ranges_m)


MAGMA_DB = 40.0  # the energyscape panels' colour scale: magma from -40 dB (dark) to 0 dB


def farthest_first_order_m(pose, size=(6.0, 4.0, 3.0), emitter_m=(0.0, 0.0, 0.05)):
    """The longest one-bounce echo in a box room [m, as a range: half the path]: emitter -> a
    surface point in front of the emitter (its piston faces the sensor's +x) -> the array centre,
    over the room's surfaces sampled every 2 cm."""
    emitter = pose[:3, :3] @ np.asarray(emitter_m) + pose[:3, 3]
    faces = []
    for axis, side in enumerate(size):
        u, v = (
            a.ravel()
            for a in np.meshgrid(*(np.linspace(0.0, s, round(s / 0.02) + 1) for k, s in enumerate(size) if k != axis))
        )
        faces += [np.insert(np.c_[u, v], axis, wall, axis=1) for wall in (0.0, side)]
    surface = np.concatenate(faces)
    surface = surface[(surface - emitter) @ pose[:3, 0] > 0]
    path = np.linalg.norm(surface - emitter, axis=1) + np.linalg.norm(surface - pose[:3, 3], axis=1)
    return float(path.max() / 2)


def loud_ranges_m(image, box, floor_db):
    """Ranges [m] of an energyscape panel's pixels louder than `floor_db` (magma read back to dB)."""
    value, distance = colormap_value(image, "magma")
    loud = (distance < 0.03) & (value * MAGMA_DB - MAGMA_DB > floor_db) & box.inside(image.shape)
    rows = np.nonzero(loud)[0]
    return IMAGE_RANGE_M[0] + (box.bottom - rows) / box.height * (IMAGE_RANGE_M[1] - IMAGE_RANGE_M[0])


def check_lidar_on_energyscape(image, box, ranges_m):
    """The cyan LiDAR cells on an energyscape panel are the beams' (azimuth, range), each drawn."""
    azimuth_deg = np.rad2deg(HOKUYO_AZIMUTH_RAD)
    seen = (np.abs(azimuth_deg) <= 90.5) & (ranges_m < IMAGE_RANGE_M[1])
    want = box.to_pixels(azimuth_deg[seen], ranges_m[seen], IMAGE_AZIMUTH_DEG, IMAGE_RANGE_M)
    drawn = near(image, "cyan", 0.1) & box.inside(image.shape)
    legend = np.nonzero(near(image, "0.8", 0.02) & box.inside(image.shape))  # its face: no magma colour is grey
    drawn[legend[0].min() - 3 : legend[0].max() + 4, legend[1].min() - 3 : legend[1].max() + 4] = False
    cyan = points_of(drawn)
    clear = (want[:, 0] > box.left + 4) & (want[:, 0] < box.right - 4)  # the spines hide the outer cells
    assert distances(cyan, densify(want)).max() <= 4.0, "a LiDAR cell where no beam returns"
    assert distances(want[clear], cyan).max() <= 4.0, "a beam's return not drawn"


def test_render_sonar_panels_differ_by_bounces_as_the_geometry_says(tmp_path, device):
    """--sonar in box_room, frame 2, max_bounces 0 above and 2 below. Left panels: echoes of order 1
    only above (one colour), orders 1-3 below (three). Right panels: with no secondary bounce every
    echo above -25 dB lies within the longest one-bounce path of the room, while max_bounces 2
    adds loud phantom echoes beyond it; the LiDAR image on top of both is the 2D ray cast's. The
    settings file holds the tracer as used (2000 rays)."""
    out = tmp_path / "sonar.png"
    argv = ["render", "--sonar", "--scene", "box_room", "--frames", "5", "--frame", "2", "--rays", "2000"]
    assert main([*argv, "--max-bounces", "2", "--device", device, "--out", str(out)]) == 0
    written = json.loads(out.with_suffix(".json").read_text())
    assert written["sim"]["tracer"]["ray_count"] == 2000 and written["options"]["max_bounces"] == 2
    image = read_rgb(out)
    frames = axes_frames(image)
    (top_0, scape_0), (top_2, scape_2) = (sorted(row, key=lambda box: box.left) for row in (frames[:2], frames[2:]))
    assert top_0.top < top_2.top and scape_0.top < scape_2.top  # max_bounces 0 is the upper row

    viridis = matplotlib.colormaps["viridis"]
    order_colours = [viridis(k / 2)[:3] for k in range(3)]  # orders 1, 2, 3 (the most either row has)
    counts = [
        [int((near(image, c, 0.05) & box.inside(image.shape)).sum()) for c in order_colours] for box in (top_0, top_2)
    ]
    assert counts[0][0] > 500 and counts[0][1] == counts[0][2] == 0, counts
    assert min(counts[1]) > 500, counts

    pose = scenes.trajectory(scenes.box_room(seed=0), frames=5, seed=0)[2]
    farthest_m = farthest_first_order_m(pose)
    first_order, multipath = loud_ranges_m(image, scape_0, -25.0), loud_ranges_m(image, scape_2, -25.0)
    assert len(first_order) > 1000 and first_order.max() < farthest_m + 0.1, (first_order.max(), farthest_m)
    assert np.sum(multipath > farthest_m + 0.3) > 1000, "no phantom echo beyond the one-bounce paths"

    _, ranges_m = first_hits(pose[:2, 3], yaw_of(pose), HOKUYO_AZIMUTH_RAD, (0.0, 0.0, 6.0, 4.0))
    for box in (scape_0, scape_2):
        check_lidar_on_energyscape(image, box, ranges_m)
