from mld_core.cli import main

raise SystemExit(main())
