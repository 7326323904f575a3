"""The executables: one node (or one process of composed nodes) a module, each with its main()."""
