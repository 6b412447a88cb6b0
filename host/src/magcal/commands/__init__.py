"""The device commands of the command line (``info``, ``collect``, ``flash``, ``verify``): one
module each, with ``add_parser(subparsers)`` setting ``run``. Thin wrappers: the work is done
in :mod:`magcal.device` and :mod:`magcal.link`; :mod:`magcal.commands.common` opens a device
the same way for all of them."""
