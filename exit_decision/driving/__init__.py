"""Drivers: everything that drives the CAVs (a learned policy on the grid or over options, the
rule-based driver, a constant option, SUMO's drivers) behind one interface (``interface``), and
the one episode loop that plays any of them in the environment (``episode``)."""
