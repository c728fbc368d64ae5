

def test_instance_masks_split_separated_blocks_of_one_type():
    import numpy as np

    from perception.data import instance_masks

    m = np.zeros((40, 60), bool)
    m[5:15, 5:15] = True  # block A
    m[20:30, 30:45] = True  # block B of the same type
    m[38:40, 0:2] = True  # 4-pixel speck: dropped
    inst = instance_masks(m, min_pixels=50)
    assert sorted(int(i.sum()) for i in inst) == [100, 150]
    assert not np.any(inst[0] & inst[1])
    m[15:20, 10:35] = True  # a bridge joins them: one instance
    assert len(instance_masks(m, min_pixels=50)) == 1
