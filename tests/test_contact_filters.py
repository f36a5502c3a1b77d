"""zoo.contact_filters: the compiled filters against velocities worked by hand and against the numpy reference."""

from __future__ import annotations

import numpy as np
from naive_filters import closing_in_time, facing_faces, relative_motion

from zoo.contact_filters import GRAZING_COS, SEPARATED_COS, Closing, usable_rows


def kept(points, depths, normals, face_normals, sdf_motion, mesh_motion, seconds, slack=0.0) -> list[bool]:
    closing = Closing(*relative_motion(sdf_motion, mesh_motion), seconds)
    return usable_rows(points, depths, normals, face_normals, *closing, GRAZING_COS, SEPARATED_COS, slack).tolist()


def test_separated_contacts_are_kept_only_where_the_step_can_close_them():
    """Velocities worked by hand: touching contacts stay, separated ones stay only while their bodies close the gap
    within 1.5 steps, rotation included."""
    up = np.tile([0.0, 0.0, 1.0], (4, 1))  # normals from the SDF body (below) to the mesh body (above)
    points = np.array([[0.0, 0.1, 0.0]] * 4)
    depths = np.array([-1e-4, 2e-3, 4e-3, 2e-3])
    at_rest = (np.zeros(3), np.zeros(6))
    rising = (np.zeros(3), np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))  # 1 m/s towards the mesh body: 3 mm in 1.5 steps
    spinning = (np.zeros(3), np.array([0.0, 0.0, 0.0, 10.0, 0.0, 0.0]))  # 10 rad/s about x: the points rise at 1 m/s
    expected = [True, True, False, True]
    seconds = 1.5 * 0.002
    assert kept(points, depths, up, up, rising, at_rest, seconds) == expected
    assert kept(points, depths, up, up, spinning, at_rest, seconds) == expected
    # the same motion given to the mesh body opens the gaps: only the touching contact stays
    assert kept(points, depths, up, up, at_rest, rising, seconds) == [True, False, False, False]
    # a spin about an axis through a point off the origin: the SDF body turning about (0, 0.1, 0) leaves the
    # points on that axis at rest
    about_the_points = (np.array([0.0, 0.1, 0.0]), spinning[1])
    assert kept(points, depths, up, up, about_the_points, at_rest, seconds) == [True, False, False, False]
    # no time given: every separated contact stays
    assert kept(points, depths, up, up, at_rest, rising, -1.0) == [True] * 4


def test_facing_contacts_by_hand():
    """A contact whose normal is 50 degrees from its face's stays touching and goes separated; one at 10 degrees stays
    either way, either side of the face; a degenerate face keeps any."""
    def tilted(degrees):
        return np.array([np.sin(np.radians(degrees)), 0.0, np.cos(np.radians(degrees))])

    normals = np.array([tilted(50), tilted(50), tilted(10), -tilted(10), tilted(80)])
    faces = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0], [0, 0, 0.0]])
    depths = np.array([-1e-4, 1e-4, 1e-4, -1e-4, 1e-4])
    closing_fast = (np.zeros(3), np.array([0.0, 0.0, 0.0, 0, 0, 0])), (np.zeros(3), np.array([0, 0, -10.0, 0, 0, 0]))
    assert kept(np.zeros((5, 3)), depths, normals, faces, *closing_fast, 0.003) == [True, False, True, True, True]


def test_a_depth_known_within_a_slack_is_taken_at_its_least():
    """A proxy's depths, known within its error bound: a contact 2 um out, at rest, 50 degrees from its face, is kept
    with a 5 um slack (it may touch: the touching tests) and dropped without one (separated, neither facing nor
    closing); one 8 um out is dropped either way, and one whose bodies close 6 um within the step is kept with the
    slack (3 um are left) and dropped without it (8 um)."""
    tilt = np.radians(50.0)
    normals = np.array([[np.sin(tilt), 0.0, np.cos(tilt)], [np.sin(tilt), 0.0, np.cos(tilt)], [0.0, 0.0, 1.0]])
    faces = np.tile([0.0, 0.0, 1.0], (3, 1))
    depths = np.array([2e-6, 8e-6, 8e-6])
    at_rest = (np.zeros(3), np.zeros(6))
    approaching = (np.zeros(3), np.array([0.0, 0.0, 2e-3, 0.0, 0.0, 0.0]))  # 2 mm/s towards the mesh body: 6 um in 3 ms
    assert kept(np.zeros((3, 3)), depths, normals, faces, at_rest, at_rest, 0.003) == [False, False, False]
    assert kept(np.zeros((3, 3)), depths, normals, faces, at_rest, at_rest, 0.003, slack=5e-6) == [True, False, False]
    assert kept(np.zeros((3, 3)), depths, normals, faces, approaching, at_rest, 0.003, slack=5e-6) == [True, False, True]
    assert kept(np.zeros((3, 3)), depths, normals, faces, approaching, at_rest, 0.003) == [False, False, False]


def test_compiled_filters_are_the_numpy_reference():
    """Random contacts (both signs of depth, normals near and far from their faces', degenerate faces, both bodies
    moving and turning): the compiled rows are the numpy reference's, row for row."""
    rng = np.random.default_rng(7)
    n = 4000
    faces = rng.normal(size=(n, 3))
    faces /= np.linalg.norm(faces, axis=1, keepdims=True)
    faces[rng.random(n) < 0.05] = 0.0
    normals = faces + rng.normal(scale=rng.choice([0.1, 1.0, 3.0], size=(n, 1)), size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = rng.normal(scale=0.1, size=(n, 3))
    depths = rng.normal(scale=2e-3, size=n)
    for slack in (0.0, 0.0, 0.0, 1e-3, 1e-3):
        sdf_motion = (rng.normal(scale=0.2, size=3), rng.normal(scale=(0.5, 0.5, 0.5, 5, 5, 5)))
        mesh_motion = (rng.normal(scale=0.2, size=3), rng.normal(scale=(0.5, 0.5, 0.5, 5, 5, 5)))
        seconds = 0.003
        expected = facing_faces(normals, faces, depths, slack) & closing_in_time(points, depths, normals, sdf_motion,
                                                                                  mesh_motion, seconds, slack)
        got = np.array(kept(points, depths, normals, faces, sdf_motion, mesh_motion, seconds, slack))
        # a closing speed within rounding of its threshold may fall either side: the rows must agree elsewhere
        (a_origin, a), (b_origin, b) = sdf_motion, mesh_motion
        speed = np.einsum("ij,ij->i", a[:3] + np.cross(a[3:], points - a_origin) - b[:3]
                          - np.cross(b[3:], points - b_origin), normals)
        at_threshold = np.abs(speed * seconds - (depths - slack)) < 1e-12
        assert (got == expected)[~at_threshold].all()
        assert 0.2 * n < expected.sum() < 0.8 * n  # both outcomes are exercised
