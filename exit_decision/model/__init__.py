"""The decision model, below both the trainer and the nodes: the Q-networks (``networks``), the
policy checkpoint and greedy inference under the shield (``policy``), and how policy runs are
named and where their files are (``names``). Nothing here imports from ``learning``,
``experiments`` or ``ros``; this package and ``names`` import no torch, so the decision node
plans its policies and answers parameter requests before torch is loaded."""
