"""Worked examples that use jaxmetrics for real training (needs the `train` extra).

`jaxmetrics.examples.ppo` is a jitted PPO on a Brax environment (MJX backend) that reports
episode, physical and learner metrics through one `MetricsState`; run it with
`python -m jaxmetrics.examples.ppo --help`. Importing this package imports nothing heavy.
"""
