"""Experience and datasets: replay buffers (off-policy), episode storage (on-policy and
offline), sequence windows (the Decision Transformer) and Minari datasets."""
