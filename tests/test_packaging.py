"""Packaging: declared dependencies match the imports, the wheel ships the configs and LICENSE,
constraints.txt pins a set the declared ranges accept, and the Makefile installs with it."""

from __future__ import annotations

import ast
import importlib.metadata
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("toolkit", "materials", "renderers", "strategies")
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PROJECT = PYPROJECT["project"]
# import name -> distribution for optional packages that need not be installed here
NOT_INSTALLED_HERE = {"gsplat": "gsplat", "ray": "ray", "open3d": "open3d", "tensorboard": "tensorboard",
                      "submitit": "submitit"}


def _requirements(entries: list[str]) -> dict[str, Requirement]:
    out = {}
    for entry in entries:
        req = Requirement(entry)
        out[canonicalize_name(req.name)] = req
    return out


DEPENDENCIES = _requirements(PROJECT["dependencies"])
EXTRAS = {name: _requirements(entries) for name, entries in PROJECT["optional-dependencies"].items()}


def _top_level_imports(files: list[Path]) -> dict[str, set[str]]:
    """Absolute imports of the files: top-level module name -> files importing it."""
    found: dict[str, set[str]] = {}
    for file in files:
        for node in ast.walk(ast.parse(file.read_text(), filename=str(file))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(str(file.relative_to(ROOT)))
    return found


def _third_party(imports: dict[str, set[str]], own: set[str]) -> dict[str, set[str]]:
    return {m: f for m, f in imports.items() if m not in sys.stdlib_module_names and m not in own}


def _distribution(module: str) -> str:
    dists = importlib.metadata.packages_distributions().get(module)
    if dists:
        return canonicalize_name(dists[0])
    if module in NOT_INSTALLED_HERE:
        return NOT_INSTALLED_HERE[module]
    raise AssertionError(f"import {module!r} maps to no installed distribution; add it to NOT_INSTALLED_HERE "
                         "in tests/test_packaging.py with its distribution name")


def _source_files() -> list[Path]:
    return [p for name in PACKAGES for p in (ROOT / name).rglob("*.py") if "__pycache__" not in p.parts]


def test_every_third_party_import_of_the_packages_is_declared():
    imports = _third_party(_top_level_imports(_source_files()), set(PACKAGES))
    declared = set(DEPENDENCIES) | {d for extra in EXTRAS.values() for d in extra}
    missing = {m: sorted(files)[:3] for m, files in imports.items() if _distribution(m) not in declared}
    assert not missing, f"imported by the packages but not declared in pyproject.toml: {missing}"
    # the core set is really imported: torch, numpy, warp, Lightning, PIL (pillow) among them
    for module, dist in [("torch", "torch"), ("numpy", "numpy"), ("warp", "warp-lang"), ("PIL", "pillow"),
                         ("yaml", "pyyaml"), ("pytorch_lightning", "pytorch-lightning")]:
        assert module in imports and dist in DEPENDENCIES, (module, dist)


def test_test_only_packages_are_in_the_test_extra_not_the_dependencies():
    source_imports = _third_party(_top_level_imports(_source_files()), set(PACKAGES))
    test_files = sorted((ROOT / "tests").glob("*.py")) + [ROOT / "conftest.py"]
    local = ({p.stem for p in (ROOT / "tests").glob("*.py")} | {p.stem for p in (ROOT / "docs" / "_ext").glob("*.py")}
             | {"tests", "conftest", "benchmarks"})
    test_imports = _third_party(_top_level_imports(test_files), set(PACKAGES) | local)
    only_tests = {_distribution(m) for m in test_imports if m not in source_imports}
    # pytest-run helpers of other packages (e.g. packaging, which pip and Lightning bring) are not ours
    only_tests -= {"packaging"}
    not_in_extra = sorted(d for d in only_tests if d not in EXTRAS["test"] and d not in DEPENDENCIES)
    assert not not_in_extra, f"imported only by tests, missing from the test extra: {not_in_extra}"
    for dist in ("kornia", "scikit-image"):
        assert dist in only_tests, f"{dist} is expected to be used by the tests only"
        assert dist in EXTRAS["test"] and dist not in DEPENDENCIES, dist


def test_no_exact_pins_and_python_floor():
    for group, reqs in {"dependencies": DEPENDENCIES, **EXTRAS}.items():
        for req in reqs.values():
            assert not any(s.operator in ("==", "===") for s in req.specifier), \
                f"{req} ({group}): pyproject.toml declares ranges; exact versions belong in constraints.txt"
    assert PROJECT["requires-python"] == ">=3.11"
    assert PROJECT["license"] == "Apache-2.0"
    assert "Apache License" in (ROOT / "LICENSE").read_text() and "Version 2.0" in (ROOT / "LICENSE").read_text()
    import yaml

    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["version"] == PROJECT["version"]
    assert cff["preferred-citation"]["title"].startswith("ProJo4D")


def test_constraints_pin_a_set_the_ranges_accept():
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            req = Requirement(line)
            (spec,) = req.specifier
            assert spec.operator == "==", line
            pins[canonicalize_name(req.name)] = spec.version
    groups = {"dependencies": DEPENDENCIES, **{f"extra {k}": v for k, v in EXTRAS.items() if k in ("test", "docs")}}
    for group, reqs in groups.items():
        for name, req in reqs.items():
            assert name in pins, f"{name} ({group}) is not pinned in constraints.txt"
            assert req.specifier.contains(pins[name], prereleases=True), \
                f"constraints.txt pins {name}=={pins[name]}, outside pyproject.toml's {group} range {req}"
    makefile = (ROOT / "Makefile").read_text()
    installs = [ln for ln in makefile.splitlines() if "pip install" in ln and "--upgrade pip" not in ln]
    assert installs and all("-c constraints.txt" in ln for ln in installs), installs


def test_package_list_names_every_package_folder():
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for name in PACKAGES for p in (ROOT / name).rglob("__init__.py")
               if "__pycache__" not in p.parts}
    assert listed - {"toolkit.configs"} == on_disk, (
        f"pyproject.toml [tool.setuptools] packages must list every package folder: missing "
        f"{sorted(on_disk - listed)}, not on disk {sorted(listed - on_disk - {'toolkit.configs'})}")
    assert PYPROJECT["tool"]["setuptools"]["package-dir"] == {"toolkit.configs": "configs"}


def test_configs_found_in_the_checkout_and_by_name():
    import toolkit

    folder = toolkit.configs_dir()
    assert sorted(p.name for p in folder.glob("*.yaml")) == sorted(p.name for p in (ROOT / "configs").glob("*.yaml"))
    assert toolkit.find_config("demo") == toolkit.find_config("demo.yaml")
    assert toolkit.find_config("pacnerf_sand").read_bytes() == (ROOT / "configs" / "pacnerf_sand.yaml").read_bytes()
    with pytest.raises(FileNotFoundError, match=r"no shipped config 'nope.yaml'.*demo\.yaml"):
        toolkit.find_config("nope")


def test_wheel_ships_configs_license_and_ranges(tmp_path):
    # build from a copy so that build/ and *.egg-info of the working tree are left alone
    src = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in (*PACKAGES, "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    out = tmp_path / "wheel"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(src),
                    "-w", str(out)], check=True, capture_output=True, timeout=120)
    (wheel,) = out.glob("projo4d-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        for cfg in sorted((ROOT / "configs").glob("*.yaml")):
            assert zf.read(f"toolkit/configs/{cfg.name}") == cfg.read_bytes(), cfg.name
        assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
        (meta_name,) = [n for n in names if n.endswith(".dist-info/METADATA")]
        meta = zf.read(meta_name).decode()
        zf.extractall(tmp_path / "site")
    assert "Requires-Python: >=3.11" in meta
    assert "Requires-Dist: torch<3,>=2.4" in meta or "Requires-Dist: torch>=2.4,<3" in meta, meta[:2000]
    # the installed layout finds its configs (no checkout beside it); -S: no site-packages, no editable finder
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import toolkit; "
            "print(toolkit.configs_dir()); print(toolkit.find_config('demo'))")
    res = subprocess.run([sys.executable, "-S", "-c", code, str(tmp_path / "site")], check=True, capture_output=True,
                         text=True, timeout=60)
    lines = res.stdout.split()
    assert lines[0] == str(tmp_path / "site" / "toolkit" / "configs")
    assert Path(lines[1]).read_bytes() == (ROOT / "configs" / "demo.yaml").read_bytes()


def test_installing_into_an_environment_with_torch_keeps_its_torch(tmp_path):
    """``pip install .`` where torch 2.x is already installed resolves against it and installs no torch.

    pip resolves a copy of the project against this environment with no package index at all
    (``--no-index``, ``--dry-run``): had the declared ranges asked for another torch or numpy, the
    resolution would fail here. The report lists what pip would install: projo4d alone. (This
    environment holds the torch of constraints.txt; the declared range accepts every 2.x from 2.4.)
    """
    import json

    src = tmp_path / "src"
    for name in (*PACKAGES, "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    report = tmp_path / "report.json"
    res = subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "--no-index", "--no-build-isolation",
                          "--quiet", "--report", str(report), str(src)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    installs = {canonicalize_name(item["metadata"]["name"]): item["metadata"]["version"]
                for item in json.loads(report.read_text())["install"]}
    assert installs == {"projo4d": PROJECT["version"]}, installs
    torch_range = DEPENDENCIES["torch"].specifier
    assert all(torch_range.contains(v) for v in ("2.4.0", "2.6.0", importlib.metadata.version("torch").split("+")[0]))
    assert not torch_range.contains("3.0.0") and not torch_range.contains("1.13.1")
