"""Measurements of label making: NSFP's speed and accuracy (`nsfp_bench`), its exported programs' timing
(`nsfp_timing`), and labelling records of your own clouds (`own_records_bench`)."""
