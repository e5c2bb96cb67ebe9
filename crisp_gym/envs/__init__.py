"""Gymnasium environments of crisp-gym (registered when :mod:`crisp_gym` is imported)."""
