"""Level-2 evaluation: metrics, closed-loop rollout, baselines, reports and plots."""
