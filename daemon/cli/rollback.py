"""`run_trainer.py rollback COMPONENT [--json]`: serve the previously promoted model again.

The promoted model of COMPONENT is demoted and the one promoted before it (its
previous_model_id) is promoted again; the pointer $HOPE_HOME/promoted/<component>.json is
rewritten, so a running BrainService switches back within a second. Rolling back again walks
further back. Torch-free: it only changes the registry and the pointer.

--json prints {"rolled_back": true, "component", "model": <now served>, "demoted": <was served>}
(Model.to_json_obj()); when there is nothing to roll back to it exits 2 with {"error": "..."}.
"""
from __future__ import annotations

import argparse
import json
import sys

from daemon.cli.registry import USAGE_EXIT, CommandError, open_registry, print_json
from hope_models.components import COMPONENTS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("component", choices=COMPONENTS, metavar="COMPONENT",
                        help=f"the component to roll back ({', '.join(COMPONENTS)})")
    parser.add_argument("--json", action="store_true", help="print the outcome as JSON on stdout")


def run(args: argparse.Namespace) -> int:
    from registry import promotion  # lazy: loads sqlalchemy

    try:
        with open_registry() as (settings, registry):
            with registry.session() as s:
                was = promotion.promoted(s, args.component)
                model = promotion.rollback(s, settings, args.component)
                assert was is not None  # rollback() raised PromotionError when nothing was promoted
                out = {"rolled_back": True, "component": args.component, "model": model.to_json_obj(),
                       "demoted": was.to_json_obj()}
    except (CommandError, promotion.PromotionError) as exc:
        if args.json:
            print(json.dumps({"rolled_back": False, "error": str(exc)}), flush=True)
        print(f"error: {exc}", file=sys.stderr)
        return USAGE_EXIT
    if args.json:
        print_json(out)
    else:
        print(f"{args.component}: now serving {out['model']['version']} (model {out['model']['id']}); "
              f"{out['demoted']['version']} (model {out['demoted']['id']}) demoted")
    return 0
