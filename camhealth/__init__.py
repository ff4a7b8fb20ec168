"""camhealth: cameras that look after themselves (physics, corruption, estimators, control)."""


def load_estimator(path_or_name, device="cpu"):
    """Load a trained estimator by shipped name or file, its network on ``device``; see
    :func:`camhealth.inference.load_estimator`."""
    from camhealth.inference import load_estimator as _load

    return _load(path_or_name, device=device)


__all__ = ["load_estimator"]
