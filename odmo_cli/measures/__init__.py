"""Network-free measures of motions (numpy in, numbers out) that training's report and the evaluation
share: `diagnostics` (APD and mode homogeneity, damping, reconstruction bounds) and `plausibility` (what
an animator sees: foot skating and contact, root speeds, kinetic features, bone variation). They import
nothing else of the package, so every layer may use them (the losses' foot contact is plausibility's);
the papers' metrics that only the evaluation computes are in evaluation/metrics.py."""
