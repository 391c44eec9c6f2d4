"""``python -m adaptnav`` is the ``adaptnav`` command."""

from adaptnav.service.cli import main

raise SystemExit(main())
