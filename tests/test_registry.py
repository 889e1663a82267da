"""The generic registry: lookup errors, built-ins and third-party entry points."""

from __future__ import annotations

import sys
import textwrap

import pytest

from materials import MATERIALS, Material, get_material
from toolkit.registry import Registry, UnknownNameError


def test_unknown_name_lists_known_and_close_matches():
    with pytest.raises(UnknownNameError) as info:
        MATERIALS.get("neo_hokean")
    msg = str(info.value)
    assert "Did you mean 'neo_hookean'" in msg
    for name in ("neo_hookean", "newtonian", "non_newtonian", "plasticine", "sand", "neo_hookean_simplicits"):
        assert name in msg


def test_duplicate_registration_is_refused():
    reg: Registry[type] = Registry("widget")

    @reg.register("a")
    class A:
        pass

    with pytest.raises(ValueError, match="already registered"):
        reg.register("a")(type("B", (), {}))
    assert reg.get("a") is A and A.registry_name == "a"


def test_entry_point_plugin_is_loaded_lazily(tmp_path, monkeypatch):
    """A material in a separately installed package (a real dist-info on sys.path) is found by name."""
    pkg = tmp_path / "foam_plugin"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        from materials.neo_hookean import NeoHookean

        class Foam(NeoHookean):
            """A third-party material reusing the neo-Hookean kernels."""
    '''))
    dist = tmp_path / "foam_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: foam-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[projo4d.materials]\nfoam = foam_plugin:Foam\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    reg = Registry("material", entry_point_group="projo4d.materials", builtin_modules=MATERIALS.builtin_modules)
    assert "foam_plugin" not in sys.modules
    assert "foam" in reg.names()
    cls = reg.get("foam")
    assert issubclass(cls, Material) and cls.__name__ == "Foam"
    assert isinstance(cls(), Material)
    # a subclass of a built-in is known by its own entry-point name, not its parent's
    assert cls().name == "foam" and get_material("neo_hookean").name == "neo_hookean"


def test_get_material_options_are_validated():
    with pytest.raises(ValueError, match="plasticine yield_rule must be 'gic' or 'pacnerf'"):
        get_material("plasticine", yield_rule="tresca")
    with pytest.raises(ValueError, match=r"has no option\(s\) \['colour'\]"):
        get_material("sand", colour="red")


def test_parameter_transforms_round_trip():
    import torch

    for name in MATERIALS.names():
        m = get_material(name)
        raw = m.to_raw(m.defaults())
        back = m.to_physical(raw)
        torch.testing.assert_close(back, m.pack(None), rtol=1e-5, atol=1e-6)
    nu = get_material("neo_hookean").param("nu")
    # tanh bound: any raw value maps inside [lo, hi]
    assert float(nu.to_physical(torch.tensor(1e3))) <= 0.49 + 1e-6 and float(nu.to_physical(torch.tensor(-1e3))) >= -0.99 - 1e-6
    assert float(nu.to_physical(torch.tensor(0.0))) == pytest.approx(-0.25)
