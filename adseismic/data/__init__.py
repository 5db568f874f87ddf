"""Data in and out: velocity models (models), seismic traces (traces; ObsPy formats), the forward
run's HDF5 store and atomic writes (store)."""
