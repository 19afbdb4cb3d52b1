"""The stages of `morphgs ablate`, one small module each, in the order the recipe runs them
(morphgs.ablation.recipe): captures, trainsets, training, testsets, refine, metrics2d, metrics3d.
Each exposes `make(work, **inputs)`, which fills a work folder from its inputs alone."""
