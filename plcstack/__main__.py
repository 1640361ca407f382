from plcstack.cli import main

raise SystemExit(main())
