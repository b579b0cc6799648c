"""The commands and options users' scripts call: a move inside ilt/ changes none of them
(issue 19). A new option is added here on purpose, never by accident."""

import click

from ilt.cli import cli

COMMANDS = {
    "": ["--version", "-v/--verbose", "-q/--quiet"],
    "bench": ["--quick", "--sizes", "--scenes", "--noise", "--solvers", "--batch", "--bounces", "--repeats",
              "--draws", "-o/--output", "--json"],
    "build-isf": ["HDR_DIR", "SPOTS_DIR", "-o/--output", "--sampling", "--min-separation", "--lit-fraction",
                  "--max-cell-radius", "--fine-degree", "--no-fine", "--fold-cells/--no-fold-cells", "--fold-transfer", "--keep-covered", "-j/--workers", "--scheduler", "--scheduler-file",
                  "--insecure", "-w/--workspace", "--force", "--json"],
    "calibrate": ["INPUTS", "-o/--output", "--times", "--order", "--max-order", "--pin-span/--free-span",
                  "--trust-ratios/--estimate-ratios",
                  "--tolerance", "--no-plot", "--force", "--json"],
    "capture": ["CONFIG", "-o/--output", "--resume", "--estimate", "--log", "-w/--workspace", "--json"],
    "centroids": ["HDR_DIR", "-o/--output", "--dark", "--threshold", "--min-snr", "--max-second", "--max-elongation",
                  "--large-factor", "--max-area", "--saturation", "--roi", "--refine", "-j/--workers", "--scheduler",
                  "--scheduler-file", "--insecure", "-w/--workspace", "--force", "--json"],
    "decompose": ["INPUTS", "--isf", "-o/--output", "--bounces", "--tol", "--cache-dir", "--no-cache", "--solver",
                  "--noise", "--regularise/--no-regularise", "--samples-only", "--accept-non-lambertian", "--no-spill", "--no-fold-transfer", "--scheduler", "--scheduler-file", "--insecure",
                  "-w/--workspace", "--force", "--json"],
    "demo": ["-o/--output", "--quick", "--force", "--json"],
    "merge": ["INPUTS", "-o/--output", "--bracket", "--times", "--dark", "--response", "--gain", "--read-noise",
              "--margin", "--color", "--compression", "-j/--workers", "--scheduler", "--scheduler-file", "--insecure",
              "-w/--workspace", "--force", "--json"],
    "refine": ["ISF_DIR", "-o/--output", "--beams", "--capture", "--min-spacing", "-w/--workspace", "--force",
               "--json"],
    "report": ["-w/--workspace", "-o/--output", "--json"],
    "rig-emulator": ["--socket", "--fault", "--speed", "--laser-on", "--laser-off"],
    "run": ["CONFIG", "-w/--workspace", "--force", "--scheduler", "--scheduler-file", "--insecure", "--json"],
    "separate": ["PHOTOS", "-o/--output", "--black", "--force", "--json"],
    "simulate": ["SCENE", "-o/--output", "--beams", "--albedo", "--seed", "--bounces", "--tracer-bounces", "--frames",
                 "--spot", "--fine", "--px-per-beam", "--gloss", "--patterns", "--force", "--json"],
    "status": ["CONFIG", "-w/--workspace", "--verify", "--json"],
}


def parameters(command: click.Command) -> list[str]:
    return ["/".join(sorted(p.opts + p.secondary_opts, key=len)) if isinstance(p, click.Option) else p.name.upper()
            for p in command.params]


def test_the_commands_and_their_options_are_the_ones_scripts_use():
    found = {"": parameters(cli)} | {name: parameters(command) for name, command in cli.commands.items()}
    assert found == COMMANDS


def test_every_option_says_what_it_does():
    silent = [f"{name} {p.opts[0]}" for name, command in cli.commands.items() for p in command.params
              if isinstance(p, click.Option) and not (p.help or "").strip()]
    assert silent == []
