"""Training: the train state, step and loop (``train``), distillation, the tokenizer's training, and what a config
costs before it runs (``plan``, ``plan_vae``, ``sizing``)."""
