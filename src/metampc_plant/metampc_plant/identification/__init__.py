"""Classical system identification baselines on recorded data: linear ARX and grey-box fits of
a plant family, and the validation protocol that scores them (docs/real_data.md).
"""
