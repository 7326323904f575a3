from exit_decision.cli import main; raise SystemExit(main())
