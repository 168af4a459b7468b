"""The modelDescription.xml of our FMUs: ``core`` what FMI 2.0 and FMI 3.0 share, ``fmi2`` and ``fmi3``
what each version writes its own way (capability flags, variable types, ModelStructure)."""
