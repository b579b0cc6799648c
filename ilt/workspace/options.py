"""The options of the stages that a run config can set, defined once.

``ilt run`` reads them from the rig TOML's [merge], [centroids], [build-isf] and
[decompose] sections (:func:`ilt.workspace.pipeline.load_run_config`, docs/workspace.md); the
stage commands (``ilt merge`` ...) take their flags, defaults and checks from the same
tables, so a config key and its long option can never mean different things. The help
texts are the command line's and stay with the commands.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import click


@dataclass(frozen=True)
class StageOption:
    """One option of a stage.

    name: the keyword the stage takes (the click parameter's name).
    flag: the long option without its dashes; the config key too, ``-`` or ``_`` alike.
    default: its value when not given (called, when callable, each time it is needed).
    type: what checks a value given on the command line (a click type; None: text,
    or a flag when the default is a bool).
    """

    name: str
    flag: str
    default: object = None
    type: click.ParamType | type | None = None

    @property
    def key(self) -> str:
        """The config key as the error messages name it (``read_noise``)."""
        return self.flag.replace("-", "_")

    def default_value(self):
        return self.default() if callable(self.default) else self.default

    def check(self, value, where: str) -> None:
        """Refuse a config value the command line would refuse (ValueError naming
        ``where`` and the key). The value itself is kept as written: a stage's
        fingerprint records its parameters as the config gives them."""
        if isinstance(self.default, bool) or self.type is None:
            wrong = isinstance(self.default, bool) and not isinstance(value, bool)
            if wrong:
                raise ValueError(f"{where}: {self.key} = {value!r}: must be true or false")
            return
        if isinstance(value, bool):   # (TOML true is not the number 1)
            raise ValueError(f"{where}: {self.key} = {value!r}: must be a number, not true or false")
        if isinstance(self.type, click.types.IntParamType) and not isinstance(value, int):
            raise ValueError(f"{where}: {self.key} = {value!r}: must be a whole number")
        try:
            if isinstance(self.type, click.ParamType):
                self.type.convert(value, None, None)
            else:
                self.type(value)
        except (click.BadParameter, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {self.key} = {value!r}: {getattr(exc, 'message', exc)}") from None


def _table(*options: StageOption) -> dict[str, StageOption]:
    return {o.name: o for o in options}


#: worker processes of a per-beam stage; a runtime option (no output depends on it)
WORKERS = StageOption("workers", "workers", lambda: os.cpu_count() or 1, click.IntRange(min=1))

#: more bounces than any scene keeps light for (a bounce keeps at most the albedo's fraction:
#: 0.99^1000 = 4e-5); without a bound a typo such as 100000000 computes for days
MAX_BOUNCES = 1000
BOUNCES = StageOption("n_bounces", "bounces", 8, click.IntRange(1, MAX_BOUNCES))

#: EXR compressions ``ilt merge`` writes: lossless only
COMPRESSIONS = ("zip:1", "zip", "zip:9", "zips", "piz")

MERGE = _table(
    StageOption("gain", "gain", 1.0, click.FloatRange(min=0, min_open=True)),
    StageOption("read_noise", "read-noise", 2.0, click.FloatRange(min=0)),
    StageOption("margin", "margin", 0.03, click.FloatRange(0, 0.5)),
    StageOption("color", "color", False),
    StageOption("compression", "compression", "zip:1", click.Choice(COMPRESSIONS)),
    WORKERS,
)

CENTROIDS = _table(
    StageOption("threshold", "threshold", 0.2, click.FloatRange(0, 1, min_open=True, max_open=True)),
    StageOption("min_snr", "min-snr", 10.0, click.FloatRange(min=0)),
    StageOption("max_second", "max-second", 0.05, click.FloatRange(min=0)),
    StageOption("max_elongation", "max-elongation", 2.0, click.FloatRange(min=1)),
    StageOption("large_factor", "large-factor", 4.0, click.FloatRange(min=1)),
    StageOption("max_area", "max-area", None, click.FloatRange(min=1)),
    StageOption("saturation", "saturation", None, float),
    # x0,y0,x1,y1 on the command line, [x0, y0, x1, y1] in a config
    StageOption("roi", "roi", None),
    StageOption("refine", "refine", False),
    WORKERS,
)

BUILD_ISF = _table(
    StageOption("sampling", "sampling", "cell", click.Choice(["cell", "point"])),
    StageOption("min_separation", "min-separation", 2.0, click.FloatRange(min=0)),
    StageOption("lit_fraction", "lit-fraction", 1e-4, click.FloatRange(min=0)),
    StageOption("max_cell_radius", "max-cell-radius", None, click.FloatRange(min=0, min_open=True)),
    StageOption("fine_degree", "fine-degree", 1, click.IntRange(0, 2)),
    StageOption("no_fine", "no-fine", False),
    StageOption("fold_cells", "fold-cells", True),
    StageOption("fold_transfer", "fold-transfer", "all", click.Choice(["flatland", "all", "off"])),
    WORKERS,
)

DECOMPOSE = _table(
    BOUNCES,
    StageOption("tol", "tol", 0.0, click.FloatRange(min=0)),
    StageOption("samples_only", "samples-only", False),
    StageOption("accept_non_lambertian", "accept-non-lambertian", False),
)
