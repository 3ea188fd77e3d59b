"""``torchtraj.envs`` in a source checkout: the environments' source is the top-level ``envs/`` folder.

An installed torchtraj has the environments at ``torchtraj/envs`` (``pyproject.toml`` maps the package
``torchtraj.envs`` to ``envs/``, and the wheel never contains this file). Run from a source tree (``PYTHONPATH`` at the
checkout, or an editable install) the import lands here instead; this module then loads ``envs/__init__.py`` under
the name ``torchtraj.envs``, with ``envs/`` as its package path, and puts it in its own place in ``sys.modules``. So
``torchtraj.envs.pendulum`` and friends are the same modules in every setting, and no top-level package named
``envs`` is installed.

Checked by ``tests/test_envs.py`` (the wheel's contents, slow) and by hand, in a fresh virtual environment::

    python -m venv /tmp/v && /tmp/v/bin/pip install -e '.[test]'     # then, as well, a plain `pip install .`
    cd / && /tmp/v/bin/python -c "import torchtraj, gymnasium, importlib.util as u; \
        gymnasium.make('torchtraj/Pendulum-v0'); import torchtraj.envs; print(u.find_spec('envs'))"   # None
"""

import importlib.util
import sys
from pathlib import Path

_SOURCE = Path(__file__).resolve().parent.parent.parent / "envs"


def _load_source_package():
    spec = importlib.util.spec_from_file_location(__name__, _SOURCE / "__init__.py",
                                                  submodule_search_locations=[str(_SOURCE)])
    if spec is None:
        raise ImportError(f"torchtraj.envs: the environments' source folder {_SOURCE} is missing")
    module = importlib.util.module_from_spec(spec)
    sys.modules[__name__] = module  # the import statement returns what sys.modules holds after this body
    spec.loader.exec_module(module)


_load_source_package()
