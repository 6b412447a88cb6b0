from magcal.cli import main

raise SystemExit(main())
