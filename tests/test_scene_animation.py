"""`hybridjax.plot.animate_scene`: what it draws checked against the closed-form motion of a
point mass that falls onto a floor and slides, and against the solution's states."""

import functools
import math

import matplotlib

matplotlib.use("Agg")

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import hybridjax as hj  # noqa: E402
import hybridjax.plot as hjp  # noqa: E402

G = 9.81
Z0, VX = 1.0, 0.5
T_LAND = math.sqrt(2 * Z0 / G)
ARGS = {"g": jnp.asarray(G)}
SAVES = np.linspace(0.0, 1.0, 11)
DRAWING = hjp.SceneDrawing(
    points={"ball": (0, 1), "shadow": lambda q, args: jnp.stack([q[0], 0.0 * q[1]])},
    segments=[("ball", "shadow")],
    contacts={"floor": "ball"},
    ground=[((-0.5, 0.0), (1.5, 0.0))],
)


@functools.cache
def solution():
    """A unit point mass (x, z) dropped from z = 1 with speed 0.5 along x onto a frictionless
    plastic floor z >= 0: it lands at sqrt(2 / g) and slides on with the floor's force g."""
    scene = hj.Scene(
        2, lambda q, p: jnp.eye(2), lambda t, q, dq, p: jnp.stack([0.0 * q[0], -p["g"] + 0.0 * q[1]]),
        [hj.Constraint("floor", lambda t, q, p: q[1])], bounds=((0.0, 0.0, -2.0, -2.0), (1.0, 1.0, 2.0, 2.0)),
    )
    system = hj.contact_system(scene, ["free"], ARGS)
    return hj.simulate(system, jnp.array([0.0, Z0, VX, 0.0]), "free", 0.0, 1.0, ARGS,
                       stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
                       saveat=jnp.asarray(SAVES))


def closed_form(t):
    """(ball, shadow, touching, floor force) at the times t."""
    t = np.asarray(t)
    x = VX * t
    z = np.where(t < T_LAND, Z0 - 0.5 * G * t**2, 0.0)
    ball = np.stack([x, z], axis=-1)
    shadow = np.stack([x, 0.0 * x], axis=-1)
    landed = t > T_LAND
    force = np.stack([0.0 * t, np.where(landed, G, 0.0)], axis=-1)
    return ball, shadow, landed, force


def test_frames_at_saved_states_follow_the_closed_form():
    sol = solution()
    frames = hjp.scene_frames(sol, DRAWING)
    ball, shadow, landed, force = closed_form(SAVES)
    np.testing.assert_allclose(frames.times, SAVES)
    np.testing.assert_allclose(frames.points[:, 0], ball, atol=1e-8)
    np.testing.assert_allclose(frames.points[:, 1], shadow, atol=1e-8)
    np.testing.assert_allclose(frames.points[:, 0], np.asarray(sol.ys)[:, :2], atol=1e-14)
    np.testing.assert_array_equal(frames.touching[:, 0], landed)
    np.testing.assert_allclose(frames.forces[:, 0], force, atol=1e-8)


def test_frames_at_given_times_are_the_dense_output():
    sol = solution()
    times = np.linspace(0.05, 0.95, 7)
    frames = hjp.scene_frames(sol, DRAWING, times=times)
    dense, _ = sol.evaluate(jnp.asarray(times))
    np.testing.assert_allclose(frames.points[:, 0], np.asarray(dense)[:, :2], atol=1e-12)
    np.testing.assert_allclose(frames.points[:, 0], closed_form(times)[0], atol=1e-8)
    np.testing.assert_allclose(frames.forces[:, 0], closed_form(times)[3], atol=1e-8)


def test_animation_draws_the_frames_in_a_notebook_and_to_a_file(tmp_path):
    sol = solution()
    fig, ax = plt.subplots()
    anim = hjp.animate_scene(sol, DRAWING, ax=ax)
    html = anim.to_jshtml()
    assert "<img" in html and "animation" in html.lower()
    # After rendering, the artists hold the last frame (t = 1): ball at (0.5, 0), resting, force g up.
    ball, shadow, _, force = closed_form(np.array([1.0]))
    dots = [ln for ln in ax.lines if ln.get_label() == "_points"][0]
    np.testing.assert_allclose(np.stack(dots.get_data(), axis=-1), np.concatenate([ball, shadow]), atol=1e-8)
    marks = [ln for ln in ax.lines if ln.get_label() == "_contacts"][0]
    np.testing.assert_allclose(np.stack(marks.get_data(), axis=-1), ball, atol=1e-8)
    (arrows,) = ax.collections
    # The largest force is drawn at a fifth of the view's width.
    width = np.diff(ax.get_xlim())[0]
    np.testing.assert_allclose(np.stack([arrows.U, arrows.V], axis=-1), 0.2 * width * force / G, atol=1e-8)
    assert ax.get_title() == "t = 1.000, floor"
    anim.save(tmp_path / "ball.gif", writer="pillow", fps=5)
    assert (tmp_path / "ball.gif").stat().st_size > 1000
    plt.close(fig)


def test_drawing_errors_name_the_field():
    with pytest.raises(ValueError, match=r"`segments\[0\]` names unknown point 'foot'"):
        hjp.SceneDrawing(points={"hip": (0, 1)}, segments=[("hip", "foot")])
    with pytest.raises(TypeError, match=r"`points\['hip'\]`"):
        hjp.SceneDrawing(points={"hip": (0, "z")})
    with pytest.raises(ValueError, match=r"`contacts\['floor'\]` names unknown point"):
        hjp.SceneDrawing(points={"hip": (0, 1)}, contacts={"floor": "foot"})
    with pytest.raises(ValueError, match="force_scale"):
        hjp.SceneDrawing(points={"hip": (0, 1)}, force_scale=-1.0)
    with pytest.raises(ValueError, match="unknown constraint 'wall'"):
        hjp.scene_frames(solution(), hjp.SceneDrawing(points={"p": (0, 1)}, contacts={"wall": "p"}))
    with pytest.raises(ValueError, match="indexes past"):
        hjp.scene_frames(solution(), hjp.SceneDrawing(points={"p": (0, 2)}))
