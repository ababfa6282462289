"""The sub-commands that compose every layer (serve, demo, infer, webapp): each has
`add_arguments(parser)` and `run(args) -> int`, like the sub-commands of the lower layers."""
