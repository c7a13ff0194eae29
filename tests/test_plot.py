"""Plots drawn with the Agg backend, checked against what the solution says was drawn."""

import matplotlib

matplotlib.use("Agg")

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pytest

import hybridjax as hj
import hybridjax.plot as hjp

from helpers import BALL, BALL_ARGS, CEILING, THERMO, TIGHT


@pytest.fixture(scope="module")
def ceiling_sol():
    return hj.simulate(CEILING, jnp.array([0.0, 7.0]), "flight", 0.0, 1.0, {"g": 9.8, "H": 2.0},
                       stepsize_controller=TIGHT)


def test_hybrid_time_domain_bars_and_zero_length_epochs(ceiling_sol, tmp_path):
    ax = hjp.hybrid_time_domain(ceiling_sol)
    bars = [p for p in ax.patches]
    epochs = ceiling_sol.hybrid_time_domain()
    positive = [e for e in epochs if e.length > 0]
    assert len(bars) == len(positive) == 2
    for bar, ep in zip(bars, positive, strict=True):
        assert bar.get_x() == pytest.approx(ep.start) and bar.get_width() == pytest.approx(ep.length)
        assert bar.get_y() + bar.get_height() / 2 == pytest.approx(ep.mode)
    diamonds = [ln for ln in ax.lines if ln.get_marker() == "D"]
    assert len(diamonds) == 1 and diamonds[0].get_xdata()[0] == pytest.approx(epochs[1].start)
    ax.figure.savefig(tmp_path / "htd.png")
    plt.close(ax.figure)


def test_trajectory_segments_per_mode_and_event_markers(tmp_path):
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 2.0, BALL_ARGS, stepsize_controller=TIGHT)
    ax = hjp.trajectory(sol, component=0, points_per_epoch=30)
    n = int(sol.num_events)
    segments = [ln for ln in ax.lines if ln.get_linestyle() == "-" and ln.get_marker() in ("None", None, "")]
    assert len(segments) == n + 1  # one line per epoch
    ev = [ln for ln in ax.lines if ln.get_marker() == "x"][0]
    np.testing.assert_allclose(ev.get_xdata(), np.asarray(sol.event_times[:n]))
    # the first epoch's line is the free fall h = 1 - g t^2 / 2
    t, h = segments[0].get_xdata(), segments[0].get_ydata()
    np.testing.assert_allclose(h, 1 - 4.9 * t ** 2, atol=1e-8)
    ax.figure.savefig(tmp_path / "traj.png")
    plt.close(ax.figure)


def test_phase_plane_with_guard_overlay_and_thermostat_modes(tmp_path):
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 1.5, BALL_ARGS, stepsize_controller=TIGHT)
    ax = hjp.phase(sol, 0, 1)
    assert len(ax.collections) >= 1  # the guard's zero set h = 0
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["flight", "events"]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x[0]", "x[1]")  # the ball's modes name no components
    assert ax.get_title() == f"phase plane: T1_REACHED, {int(sol.num_events)} events"
    plt.close(ax.figure)
    p = dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)
    th = hj.simulate(THERMO, jnp.array([19.0]), "off", 0.0, 20.0, p, stepsize_controller=TIGHT)
    ax = hjp.trajectory(th, 0)
    colours = {tuple(np.round(ln.get_color(), 3)) for ln in ax.lines if ln.get_marker() in ("None", None, "")
               and ln.get_linestyle() == "-"}
    modes = set(np.asarray(th.epoch_modes[: int(th.num_events) + 1]).tolist())
    assert len(colours) == len(modes)  # one colour per mode visited
    ax.figure.savefig(tmp_path / "thermo.png")
    plt.close(ax.figure)


@pytest.fixture(scope="module")
def ball_batch():
    run = jax.jit(jax.vmap(lambda h, e: hj.simulate(BALL, jnp.stack([h, 0 * h]), "flight", 0.0, 4.0,
                                                     {"g": 9.8, "e": e}, saveat=jnp.linspace(0, 4, 50),
                                                     max_epochs=16)))
    return run(jnp.linspace(0.5, 1.5, 12), jnp.linspace(0.4, 0.85, 12))


def test_batch_status_and_zeno_histograms_and_graph(ball_batch, tmp_path):
    sol = ball_batch
    ax = hjp.batch(sol, 0)
    assert len(ax.lines) == 12
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["flight"]  # colour = mode
    assert ax.get_ylabel() == "x[0]"
    plt.close(ax.figure)
    ax = hjp.status_histogram(sol)
    heights = {p.get_x(): p.get_height() for p in ax.patches}
    assert sum(heights.values()) == 12
    plt.close(ax.figure)
    ax = hjp.zeno_histogram(sol)
    zeno = int(np.sum(np.asarray(sol.status_code) == hj.STATUS_NAMES.index("ZENO")))
    assert sum(p.get_height() for p in ax.patches) == zeno > 0
    plt.close(ax.figure)
    ax = hjp.transition_graph(THERMO)
    arrows = [p for p in ax.patches if p.get_label().startswith("transition")]
    assert len(arrows) == THERMO.num_transitions
    ax.figure.savefig(tmp_path / "graph.png")
    plt.close(ax.figure)


def test_html_reprs(ceiling_sol):
    html = CEILING._repr_html_()
    assert html.count("<tr>") == 1 + 2 + 1 + 2  # headers and rows: 2 modes, 2 transitions
    assert "impact" in html and "lift-off" in html
    s = ceiling_sol._repr_html_()
    assert "T1_REACHED" in s and s.count("&rarr;") == 2


# A hopper whose modes differ in dimension: flight (h, v) falls freely; at touchdown h = 0 the
# state becomes the stance compression c (1-D), which grows at unit rate.
_FLIGHT = hj.Mode("flight", lambda t, x, p: jnp.array([x[1], -p["g"] + 0.0 * x[1]]), dim=2,
                  names=("h", "v"))
_STANCE = hj.Mode("stance", lambda t, x, p: jnp.ones_like(x), dim=1, names=("c",))
HOPPER = hj.HybridSystem([_FLIGHT, _STANCE], [hj.Transition(
    "flight", "stance", guard=lambda t, x, p: x[0], reset=lambda t, x, p: 0.0 * x[:1], name="touchdown")])


@pytest.fixture(scope="module")
def hopper_sol():
    return hj.simulate(HOPPER, jnp.array([1.0, 0.0]), "flight", 0.0, 0.8, {"g": 9.8},
                       stepsize_controller=TIGHT)


def test_mode_component_names_default_and_validation():
    flow = lambda t, x, p: x  # noqa: E731
    assert _FLIGHT.component_names == ("h", "v") and _STANCE.names == ("c",)
    assert hj.Mode("m", flow, dim=3).component_names == ("x[0]", "x[1]", "x[2]")
    assert hj.Mode("m", flow, 2, None, ["a", "b"]).names == ("a", "b")  # positional, a list
    with pytest.raises(ValueError, match=r"Mode 'stance'.*2 entries but `dim` is 1"):
        hj.Mode("stance", flow, dim=1, names=("c", "d"))
    with pytest.raises(TypeError, match=r"Mode 'flight'.*tuple of non-empty strings"):
        hj.Mode("flight", flow, dim=2, names="hv")


def test_trajectory_labels_modes_of_different_dimension_and_plots_a_function(hopper_sol, tmp_path):
    sol = hopper_sol
    t_td = np.sqrt(2 / 9.8)  # touchdown of a fall from h = 1
    assert int(sol.num_events) == 1
    np.testing.assert_allclose(sol.event_times[0], t_td, atol=1e-8)
    # Component 0 means h in flight and c in stance: both named, one legend entry per mode.
    ax = hjp.trajectory(sol, 0, points_per_epoch=20)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["flight: h", "stance: c", "events"]
    assert ax.get_ylabel() == "h / c"
    assert ax.get_title() == "trajectory: T1_REACHED, 1 event"
    plt.close(ax.figure)

    # One quantity in both modes: the height, h in flight and -c in stance.
    def height(mode, x):
        return x[0] if mode == "flight" else -x[0]

    ax = hjp.trajectory(sol, height, points_per_epoch=20)
    assert ax.get_ylabel() == "height"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["flight", "stance", "events"]
    fl, st = [ln for ln in ax.lines if ln.get_label() in ("flight", "stance")]
    t = fl.get_xdata()
    np.testing.assert_allclose(fl.get_ydata(), 1 - 4.9 * t ** 2, atol=1e-8)
    t = st.get_xdata()
    np.testing.assert_allclose(st.get_ydata(), -(t - t_td), atol=1e-8)
    ev = [ln for ln in ax.lines if ln.get_marker() == "x"][0]
    np.testing.assert_allclose(ev.get_ydata(), [0.0], atol=1e-8)  # h at touchdown
    ax.figure.savefig(tmp_path / "hopper.png")
    plt.close(ax.figure)
    ax = hjp.hybrid_time_domain(sol)
    assert ax.get_title().endswith("T1_REACHED")
    plt.close(ax.figure)


def test_batch_of_a_function_and_notes_where_there_is_nothing_to_plot(ball_batch):
    sol = ball_batch
    ax = hjp.batch(sol, lambda mode, x: 0.5 * x[1] ** 2 + 9.8 * x[0])  # energy per unit mass
    assert ax.get_ylabel() == "f(mode, x)"
    e0 = 9.8 * np.linspace(0.5, 1.5, 12)  # at t = 0, at rest at height h
    np.testing.assert_allclose([ln.get_ydata()[0] for ln in ax.lines], e0, rtol=1e-12)
    plt.close(ax.figure)
    status = np.asarray(sol.status_code)
    not_zeno = sol[status != hj.Status.ZENO]
    ax = hjp.zeno_histogram(not_zeno)
    notes = [t.get_text() for t in ax.texts]
    assert notes == [f"no Zeno execution among {int(np.sum(status != hj.Status.ZENO))}"]
    assert not ax.patches
    plt.close(ax.figure)
