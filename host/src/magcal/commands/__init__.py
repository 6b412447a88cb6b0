"""The commands of the command line beyond simulate and calibrate: one module each, with
``add_parser(subparsers)`` setting ``run``; :func:`magcal.cli.build_parser` registers every
module here that has one. Thin wrappers: the work is done in :mod:`magcal.device`,
:mod:`magcal.link` and the other packages; :mod:`magcal.commands.common` opens a device the
same way for all of them."""
