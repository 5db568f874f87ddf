"""Data in and out: velocity models (models), observed seismic data (traces: the data objects and
TraceError; geometry: local frame, projection and checks; preprocess: onto the simulation's time
axis; read / write: ObsPy formats), the forward run's HDF5 store (store) and atomic writes (atomic)."""
