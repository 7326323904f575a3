"""Running the stack: the node table, the launcher, the CPU split, real-time priority, `bench ros`."""
