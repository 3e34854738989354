"""Model reduction: modal analysis (Lanczos), SLDM, the modal oscillator's closed forms,
cubature and the reduced nonlinear models (modes + modal derivatives)."""
