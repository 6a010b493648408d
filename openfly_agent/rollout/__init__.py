"""Level-2 closed loop shared by evaluation, DAgger and the RL stage: the policy protocol, the lockstep runner and
its hooks, the agent as a policy, the episode record, the dataset episode as a simulator task, and the metrics
and profiles that score an episode (docs/EVAL.md, docs/METRICS.md)."""
