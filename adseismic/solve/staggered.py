"""What the Setups of the staggered velocity-stress physics (elastic, vti, viscoacoustic) share: the receivers'
components and the verbs of the shared time loop (solve/loop.py) that do not depend on the physics."""

import warp as wp

COMPONENTS = ("vx", "vz", "pressure")  # the order of the data arrays new_data gives and the launch helpers' record fills


class StaggeredSetup:
    """Mixin of the loop verbs common to the staggered physics' Setups. A Setup provides prop (its launch helper:
    new_state, step(st, mat, sources, n, out, clock), record(st, data, receiver_op, k, clock)), receivers (S, n, 2)
    and receiver_op, and the physics' own verbs: model, sources_of, fields, key, loop_kernels, inputs."""

    period = 2  # a captured loop steps into a second state and back
    lookahead = 1  # a step reads source sample n + 1

    def fill_model(self, mat):
        for a, b in zip(mat, self.model()):
            wp.copy(a, b)

    def advance(self, st, mat, src, data, k, n, out, clock):
        self.prop.record(st, data, self.receiver_op, k, clock)
        return self.prop.step(st, mat, src, n, out, clock)

    def record(self, st, data, k, clock):
        self.prop.record(st, data, self.receiver_op, k, clock)

    def new_data(self, n, requires_grad=False):
        shape = (self.prop.n_shots, self.receivers.shape[1], n)
        return tuple(wp.zeros(shape, dtype=self.prop.dtype, device=self.prop.device, requires_grad=requires_grad) for _ in COMPONENTS)

    def new_level(self):
        return self.prop.new_state(requires_grad=True)

    def spare(self, st):
        return self.prop.new_state()

    def out_state(self, st, spare):
        return spare

    def freed(self, st):
        return st
