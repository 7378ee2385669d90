"""Running a render: progressive photon mapping in this process (progressive) or on a Dask cluster
(executor).
"""
