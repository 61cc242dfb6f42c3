"""Worked examples that use jaxmetrics for real training (needs the `train` extra).

`jaxmetrics.examples.ppo` is a jitted PPO on a Brax environment (MJX backend) or a MuJoCo
Playground one that reports episode, physical and learner metrics through one
`MetricsState`; run it with `python -m jaxmetrics.examples.ppo --help`.
`jaxmetrics.examples.brax_ppo` trains with Brax's own PPO trainer, changed in one argument,
and the reporting wrapper reports from inside it: `python -m jaxmetrics.examples.brax_ppo`.
Importing this package imports nothing heavy.
"""
