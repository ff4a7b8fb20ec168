"""camhealth: cameras that look after themselves (physics, corruption, estimators, control)."""


def load_estimator(path_or_name):
    """Load a trained estimator by shipped name or file; see :func:`camhealth.inference.load_estimator`."""
    from camhealth.inference import load_estimator as _load

    return _load(path_or_name)


__all__ = ["load_estimator"]
