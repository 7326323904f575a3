"""How policy runs are named, free of torch: the decision node plans what it will load (and
answers parameter requests) before it imports the policy module."""

#: run names of mode-conditioned policies end so: policies/mdgqn_conditioned/policy.pt
CONDITIONED_SUFFIX = '_conditioned'
