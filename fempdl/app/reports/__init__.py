"""Reports over several runs: the PRDP trade-off sweep and the method-against-Adam comparison."""
