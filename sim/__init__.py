"""The simulated world: quadrotor physics, truth models, scenarios, the in-process experiment runner."""
