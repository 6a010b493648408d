"""Level-2 closed loop shared by evaluation and DAgger: the policy protocol, the lockstep runner and its hooks,
the agent as a policy, the episode record and the dataset episode as a simulator task (docs/EVAL.md)."""
