from ffrecon.cli import main

raise SystemExit(main())
