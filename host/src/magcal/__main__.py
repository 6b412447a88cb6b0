# SPDX-License-Identifier: Apache-2.0
from magcal.cli import main

raise SystemExit(main())
