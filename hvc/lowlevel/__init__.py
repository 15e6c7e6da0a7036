"""Low-level motor skills: training and evaluating the tracking experts, and the expert
library. The tracking task they are trained on, and its reward, are tasks like any other
(hvc.envs.tracking, hvc.envs.tracking_reward)."""
