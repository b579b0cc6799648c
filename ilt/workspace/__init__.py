"""A scan's workspace: ``ilt run`` chains the stages, ``ilt status`` says which are
up to date, ``ilt demo`` and ``ilt simulate`` make scenes to run them on.

``options`` (each stage's configurable options, defined once for the commands and the
rig TOML), ``pipeline`` (``ilt run`` and ``ilt status``), ``simulate`` (exact scenes
written as ISF directories with ground truth), ``demo`` (``ilt demo``).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "demo": ["run_demo"],
        "options": ["StageOption"],
        "pipeline": ["load_run_config", "run_pipeline", "workspace_status"],
        "simulate": ["write_simulation"],
    },
)
