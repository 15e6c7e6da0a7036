import torch

from hvc.agents.network import AgentSpec, HighLevelAgent, ImageEncoder


def test_image_encoder_on_64x64_uint8():
    enc = ImageEncoder()
    out = enc(torch.randint(0, 255, (2, 3, 64, 64, 3), dtype=torch.uint8))
    assert out.shape == (2, 3, 256)


def test_agent_shapes_and_episode_resets():
    spec = AgentSpec(proprio_size=136, task_size=3, action_size=105, discrete=True, lstm_size=128,
                     value_mlp=(128, 1))
    agent = HighLevelAgent(spec)
    T, B = 4, 2
    args = (torch.randn(T, B, 136), torch.randn(T, B, 3), torch.randn(T, B), torch.randint(0, 105, (T, B)))
    logits, h, state = agent(*args, agent.initial_state(B))
    assert logits.shape == (T, B, 105) and h.shape == (T, B, 128) and agent.values(h).shape == (T, B)
    # a done at step 2 makes steps 2.. independent of what came before
    done = torch.zeros(T, B)
    done[2] = 1
    _, h_reset, _ = agent(*args, agent.initial_state(B), done=done)
    tail = tuple(a[2:] for a in args)
    _, h_fresh, _ = agent(*tail, agent.initial_state(B))
    torch.testing.assert_close(h_reset[2:], h_fresh)


def test_vision_and_continuous_heads():
    spec = AgentSpec(proprio_size=136, task_size=0, action_size=1, discrete=False, lstm_size=256,
                     value_mlp=(200, 200, 1), vision=True, critic_takes_action=True)
    agent = HighLevelAgent(spec)
    T, B = 2, 3
    out, h, _ = agent(torch.randn(T, B, 136), torch.zeros(T, B, 0), torch.zeros(T, B), torch.zeros(T, B, 1),
                      agent.initial_state(B), image=torch.randint(0, 255, (T, B, 64, 64, 3), dtype=torch.uint8))
    mean, sigma = agent.gaussian(out, -1.5, 1.5)
    assert mean.shape == (T, B, 1) and torch.all(mean.abs() <= 1.5)
    assert torch.all((sigma >= 0.1) & (sigma <= 1.0))
    assert agent.values(h, mean).shape == (T, B)
