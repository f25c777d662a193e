"""The scene of `render` and `calibrate`, from their options: a builder (--scene, --scene-arg), an
SVG floor plan (--svg) or a mesh file (--mesh, read as --up, --units and --materials say)."""

from __future__ import annotations

import json

MESH_ONLY = ("up", "units", "materials")
"""render's options that say how to read a --mesh file (cli_text.MESH_OPTIONS); None when not given."""


BUILDER_NAMES = ("box_room", "corridor", "office", "polygon_room", "random_world")
"""scenes.BUILDERS' names (tests hold them equal), known without importing scenes: trimesh and SciPy
take ~1 s to import, which `--help` and a mistyped option's refusal need not wait for."""


def add_scene_options(parser, mesh_options: dict, *, default: str = "office") -> None:
    """--scene (one of scenes.BUILDERS) or --svg or --mesh, how to read a mesh, and --scene-arg."""
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--scene", choices=BUILDER_NAMES, default=default, help="scene builder")
    source.add_argument("--svg", help="SVG floor plan to extrude instead of a builder")
    source.add_argument("--mesh", help="mesh file (any format trimesh loads) instead of a builder")
    for flag, options in mesh_options.items():  # --up, --units, --materials
        parser.add_argument(flag, **options)
    parser.add_argument(
        "--scene-arg",
        action="append",
        metavar="KEY=VALUE",
        help="extra builder argument, e.g. clutter=high or size=[10,8,3] (repeatable)",
    )


def check_mesh_options(args) -> None:
    """Refuse --up, --units or --materials without --mesh: given to a builder or a floor plan they
    would change nothing, and the picture would not be what was asked for."""
    given = [f"--{name}" for name in MESH_ONLY if getattr(args, name) is not None]
    if given and not args.mesh:
        source = f"--svg {args.svg}" if args.svg else f"--scene {args.scene}"
        options, verb = " and ".join(given), "applies" if len(given) == 1 else "apply"
        raise ValueError(
            f"{options} {verb} to --mesh only (how to read a mesh file), and this render draws {source}: "
            f"give --mesh FILE, or drop {options}"
        )


def scene_from_args(args):
    """The scene (`scenes.Scene`) of render's options; a builder's refusal names the options given."""
    import scenes

    check_mesh_options(args)
    kwargs = {}
    for item in args.scene_arg or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--scene-arg expects KEY=VALUE, got {item!r}")
        try:
            kwargs[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            kwargs[key.replace("-", "_")] = value
    if "seed" in kwargs:  # the builder's seed is --seed's (it seeds the drive and noise too)
        raise ValueError("--scene-arg seed: give the seed with --seed")
    given = " ".join(f"--scene-arg {k}={json.dumps(v)}" for k, v in kwargs.items())
    if args.svg:
        source, build, path = f"--svg {args.svg}", scenes.from_svg, (args.svg,)
    elif args.mesh:
        source, build, path = f"--mesh {args.mesh}", scenes.from_mesh, (args.mesh,)
        frame = {"up": args.up or "auto", "units": args.units or "auto", "materials": args.materials}
        kwargs = frame | {"report": print} | kwargs
    else:
        source, build, path = f"--scene {args.scene}", scenes.BUILDERS[args.scene], ()
        kwargs = {"seed": args.seed} | kwargs
    try:
        return build(*path, **kwargs)
    except (TypeError, ValueError) as err:  # SceneError names its field; an unknown or mistyped argument may not
        if isinstance(err, ValueError) and not given:  # nothing of the user's to add: it names its file
            raise
        raise ValueError(f"{source} {given}: {err}; see help(scenes.{build.__name__})") from None
