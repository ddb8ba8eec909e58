"""The dynamics model and its training, rollout and data: ``state`` (the state split), ``config`` (sizes, presets,
the training knobs), ``model`` (ActionGPT and PoseGPT, two causal RoPE transformers over the scene's frames),
``data``, ``train``, ``rollout``, ``checkpoint``."""
