"""The RiskFlow adversary: window data, encoder, MeanFlow generator, guidance, policy."""
