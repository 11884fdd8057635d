"""The files odmo writes for people and other tools (docs/formats.md): samples files (.npz) and
BVH. Checkpoints are `odmo_cli.checkpoint`'s; motion folders are the data layer's."""
