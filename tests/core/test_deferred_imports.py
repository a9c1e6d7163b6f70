"""QuickNav defers seaborn and matplotlib.pyplot (imported by gymnax's Pong and Catch; QuickNav
never uses seaborn, and pyplot only where it draws): building an env imports neither, and a user's
own seaborn or pyplot still works in the same process, however it is imported. The evaluation
imports scipy.stats only where it computes a statistic (``eval.aggregate``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from quicknav_core.deferred_imports import DeferredModule, defer_unused_imports


def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_deferred__building_an_env_or_importing_the_eval_imports_neither_seaborn_nor_scipy_stats():
    out = _run("""
        import sys
        from quicknav_core.config import EnvConfig
        import gymnax.environments.misc.pong  # the module that imports seaborn
        env, params = EnvConfig(grid_size=8).build("train")
        from quicknav_core.eval.evaluate import run_eval  # statistics import scipy.stats when used
        print(type(sys.modules["seaborn"]).__name__, "scipy.stats" in sys.modules,
              "pandas" in sys.modules, type(sys.modules["matplotlib.pyplot"]).__name__,
              "matplotlib.backend_bases" in sys.modules)
    """)
    assert out.split() == ["DeferredModule", "False", "False", "DeferredModule", "False"]


@pytest.mark.parametrize(
    "how",
    [
        "import matplotlib.pyplot\nplt = matplotlib.pyplot",  # the package's attribute
        "from matplotlib import pyplot as plt",
        "import matplotlib.pyplot as plt",
        "import matplotlib\nmatplotlib.use('Agg')\nimport matplotlib.pyplot as plt",  # use() switches pyplot
    ],
)
def test_deferred__pyplot_works_however_it_is_imported_after_the_env(how):
    out = _run(f"""
        import sys
        from quicknav_core.config import EnvConfig
        env, params = EnvConfig(grid_size=8).build("train")
        {how.replace(chr(10), chr(10) + " " * 8)}
        fig, ax = plt.subplots()
        ax.plot([0, 1], [1, 0])
        real = sys.modules["matplotlib.pyplot"]
        import matplotlib
        from gymnax.environments.bsuite import catch
        print(type(real).__name__, matplotlib.pyplot is real, catch.plt.gcf() is fig,
              matplotlib.get_backend().lower())
    """)
    assert out.split() == ["module", "True", "True", "agg"]


def test_deferred__seaborn_works_on_first_use_and_replaces_the_stand_in():
    out = _run("""
        import sys
        import quicknav_core
        import seaborn
        from gymnax.environments.misc import pong
        palette = pong.sns.color_palette("cubehelix", 3)  # gymnax's own use of it
        import seaborn.palettes as palettes
        real = sys.modules["seaborn"]
        print(len(palette), type(real).__name__, real.palettes is palettes,
              sys.modules["seaborn.palettes"] is palettes, seaborn.color_palette is real.color_palette)
    """)
    assert out.split() == ["3", "module", "True", "True", "True"]


def test_deferred__a_submodule_imported_first_loads_the_package_once():
    out = _run("""
        import sys
        import quicknav_core
        import seaborn.palettes as palettes
        real = sys.modules["seaborn"]
        print(type(real).__name__, real.palettes is palettes)
    """)
    assert out.split() == ["module", "True"]


def test_deferred__leaves_imported_and_missing_modules_alone():
    assert defer_unused_imports(("sys", "no_such_module_quicknav")) == []
    assert not isinstance(sys.modules["sys"], DeferredModule)
    assert "no_such_module_quicknav" not in sys.modules


@pytest.mark.parametrize("attr", ["__version__", "color_palette"])
def test_deferred__the_stand_in_answers_from_the_real_module(attr, monkeypatch):
    import importlib.util

    monkeypatch.delitem(sys.modules, "seaborn", raising=False)
    stand_in = DeferredModule(importlib.util.find_spec("seaborn"))
    monkeypatch.setitem(sys.modules, "seaborn", stand_in)
    value = getattr(stand_in, attr)
    assert sys.modules["seaborn"] is not stand_in
    assert value is getattr(sys.modules["seaborn"], attr)
