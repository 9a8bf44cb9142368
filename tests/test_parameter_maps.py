"""Parameter maps of the controls: values, inverses, derivatives and the gradients through them.

Each built-in map is checked entry by entry against central differences and its inverse; the
controls taking ``map=`` are checked end to end (adjoint gradient vs central differences along a
random direction per block and along the gradient, Taylor rate 2), in a static and a BDF2 run.
The how-to's map (docs/examples/howto_extend.py), outside the package, proves that a new
parametrisation is one class.
"""

import numpy as np
import pytest
from demo_modules import load_docs_example
from gradient_scenes import CONTROLS, Case, check_case, scene_model

from diffsolids.controls import (
    Affine,
    Compose,
    ControlError,
    Identity,
    Log,
    ParameterControl,
    Power,
    Simp,
)

# the how-to's map (docs/examples/howto_extend.py), checked here in depth
Sigmoid = load_docs_example("howto_extend").Sigmoid


MAPS = {
    "identity": (Identity(), [-2.0, 0.3, 5.0]),
    "log": (Log(), [-1.0, 0.0, 2.5]),
    "affine": (Affine(-3.0, 2.0), [-1.0, 0.5, 4.0]),
    "power": (Power(2.5), [0.2, 1.0, 3.0]),
    "simp": (Simp(0.1, 10.0, 3.0), [0.05, 0.5, 0.99]),
    "compose": (Compose(Simp(1.0, 2.0), Log(), Affine(0.5)), [0.1, 0.6, 0.9]),
    "sigmoid": (Sigmoid(2.0, 5.0), [-3.0, 0.0, 1.7]),
}


@pytest.mark.parametrize("name", list(MAPS))
def test_map_inverse_and_derivative(name):
    m, q = MAPS[name]
    q = np.array(q)
    p = m.forward(q)
    assert np.allclose(m.inverse(p), q, rtol=1e-12, atol=1e-14)
    h = 1e-6 * (1.0 + np.abs(q))
    fd = (m.forward(q + h) - m.forward(q - h)) / (2 * h)
    assert np.allclose(m.derivative(q), fd, rtol=1e-7)
    g = np.array([1.5, -0.5, 2.0])
    assert np.allclose(m.pullback(q, g), g * fd, rtol=1e-7)
    assert np.all(np.abs(m.derivative(q)) > 0)


@pytest.mark.parametrize(
    ("m", "bad", "match"),
    [
        (Log(), [1.0, -2.0], "positive values"),
        (Power(2.0), [-1.0], "nonnegative"),
        (Simp(1.0, 2.0), [3.0], r"values must lie in \[1, 2\]"),
    ],
)
def test_values_outside_the_range_are_refused(m, bad, match):
    with pytest.raises(ControlError, match=match):
        m.inverse(np.array(bad))


def test_bad_maps_and_arguments_are_refused():
    with pytest.raises(ControlError, match="low < high"):
        Simp(2.0, 1.0)
    with pytest.raises(ControlError, match="positive exponent"):
        Power(0.0)
    with pytest.raises(ControlError, match="nonzero scale"):
        Affine(0.0)
    model = scene_model("2d-p1-lin-cg1-ps")
    with pytest.raises(ControlError, match="either map= or log=True"):
        ParameterControl(model, "E", "field", log=True, map=Log())
    with pytest.raises(ControlError, match="must be a ParameterMap"):
        ParameterControl(model, "E", "field", map=np.exp)
    # E of this scene reaches 480: outside the SIMP range [1, 100]
    with pytest.raises(ControlError, match="coefficient 'E' cannot be parametrised: SIMP"):
        ParameterControl(model, "E", "field", map=Simp(1.0, 100.0))


def test_control_reads_back_the_parameters_it_wrote():
    model = scene_model("2d-p1-lin-cg1-ps")
    control = ParameterControl(model, "E", "field", map=Simp(100.0, 1000.0))
    q = control.value()
    assert np.all((q > 0) & (q < 1))
    low, high = control.bounds()
    assert np.all(low == 0.0) and np.all(high == 1.0)
    q2 = np.clip(q + 0.05 * np.sin(np.arange(q.size)), 0.01, 0.99)
    control.assign(q2)
    assert np.allclose(control.value(), q2, rtol=1e-12)
    assert np.allclose(model.coefficients["E"].x.array.min(), 100.0 + 900.0 * q2.min() ** 3)


MAP_CASES = [
    Case("2d-p1-lin-cg1-ps", "static", ("young-field-simp", "gravity-power"), "stress"),
    Case("2d-p1-lin-damped-lame", "bdf2", ("mu-bodies-log-affine", "young-sigmoid"), "target"),
    Case("2d-p1-nh-cg1-ps", "bdf2", ("young-field-simp", "initial-v0"), "com"),
]


@pytest.mark.parametrize("case", MAP_CASES, ids=lambda c: c.id)
def test_gradient_through_parameter_maps(case, monkeypatch):
    # a control with the map written above: lmbda per body in (50, 2000)
    monkeypatch.setitem(
        CONTROLS,
        "young-sigmoid",
        lambda sim: ParameterControl(sim.model, "lmbda", "bodies", map=Sigmoid(50.0, 2000.0)),
    )
    check_case(case)
