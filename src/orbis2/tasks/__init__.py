"""Training tasks: what each training stage plugs into the one loop of :mod:`orbis2.train`.

A task owns a stage's model, data stream, loss and evaluation; the loop owns
optimisation, checkpoints, resuming, DDP and logging. ``tokenizers`` holds the
detail (VQGAN) and abstract (teacher-aligned) tokenizers of paper Sec. 3.2,
``instrument`` the learned inverse-dynamics instrument of the steering evaluation.
"""
