"""Flax Linen models of camrep: GQN-rooms encoder, decoders and shared layers (digest section 2)."""

from camrep.models.decoder import CarDecoder as CarDecoder
from camrep.models.decoder import CarDecoderTiny as CarDecoderTiny
from camrep.models.decoder import CarSceneTable as CarSceneTable
from camrep.models.decoder import GibsonDecoder as GibsonDecoder
from camrep.models.decoder import GibsonDecoderTiny as GibsonDecoderTiny
from camrep.models.decoder import GibsonSceneTable as GibsonSceneTable
from camrep.models.decoder import GQNDecoder as GQNDecoder
from camrep.models.decoder import GQNDecoderTiny as GQNDecoderTiny
from camrep.models.decoder import ResAdaINDecoder as ResAdaINDecoder
from camrep.models.decoder import SevenScenesDecoder as SevenScenesDecoder
from camrep.models.decoder import SevenScenesSceneTable as SevenScenesSceneTable
from camrep.models.decoder import UpConvDecoder as UpConvDecoder
from camrep.models.encoder import GQN_GENERATOR_HEADS as GQN_GENERATOR_HEADS
from camrep.models.encoder import GQNEncoder as GQNEncoder
from camrep.models.encoder import GQNEncoderTiny as GQNEncoderTiny
from camrep.models.encoder import Head as Head
from camrep.models.encoder import SceneEncoder as SceneEncoder
from camrep.models.layers import SceneTable as SceneTable
from camrep.models.layers import adain as adain
from camrep.models.layers import instance_norm as instance_norm
from camrep.models.layers import intermediate_shapes as intermediate_shapes
from camrep.models.layers import lrelu as lrelu
from camrep.models.layers import param_count as param_count
from camrep.models.layers import upsample2 as upsample2
