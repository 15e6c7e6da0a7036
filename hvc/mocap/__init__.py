"""Motion-capture clips: CMU ASF/AMC and cgspeed BVH conversion to dm_control's
HDF5 reference-trajectory layout, and one loader for converted and fitted clips."""
