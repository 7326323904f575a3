"""The decision model, below both the trainer and the nodes: the Q-networks (``networks``), the
policy checkpoint and greedy inference under the shield (``policy``), how policy runs are named
and where their files are (``names``), and the modes as the weights a policy decides for
(``modes``). Nothing here imports from ``learning``, ``experiments`` or ``ros``; this package
and ``names`` and ``modes`` import no torch, so the decision node plans its policies and answers
parameter requests before torch is loaded."""
